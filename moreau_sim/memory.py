"""What one Pinocchio Data costs and the limit on it: Pinocchio 4.1 allocates four nv x nv x nv tensors in every Data
(upstream stack-of-tasks/pinocchio#2949), so a Data of a large model is refused in one line naming the scene and its
size before it is allocated (check_data_size, new_data), against the memory available or $MOREAU_SIM_DATA_LIMIT_GB."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import pinocchio as pin

from .errors import SceneError

DATA_BYTES_PER_NV3 = 32  # Pinocchio 4.1's Data: four nv x nv x nv tensors of doubles (second-order derivatives)
DATA_PEAK = 2  # createData's peak RSS is twice that (measured at nv = 300: 1.70 GB for 0.86 GB of tensors)
DATA_LIMIT_VARIABLE = "MOREAU_SIM_DATA_LIMIT_GB"  # overrides the limit of check_data_size [GiB]


MEMORY_PROBE_SECONDS = 0.5  # [s] available_memory's reading is reused this long (a run makes several Datas)
_memory_probe: list = [-math.inf, None]  # (time.monotonic() of the last reading, its bytes)


def available_memory() -> int | None:
    """Bytes of memory this process may still allocate: Linux MemAvailable, or less under a
    cgroup v2 memory limit (a container's memory.max minus memory.current); None if unknown.
    Read at most once every MEMORY_PROBE_SECONDS (the files of /proc and /sys cost ~40 us a reading)."""
    now = time.monotonic()
    if now - _memory_probe[0] < MEMORY_PROBE_SECONDS:
        return _memory_probe[1]
    avail = _read_available_memory()
    _memory_probe[:] = [now, avail]
    return avail


def _read_available_memory() -> int | None:
    avail = None
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            avail = next((int(line.split()[1]) * 1024 for line in f if line.startswith("MemAvailable:")), None)
    except (OSError, ValueError, IndexError):
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError, AttributeError):
            return None
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
            avail = min(avail, max(int(limit) - used, 0))
    except (OSError, ValueError):
        pass
    return avail


def _data_message(model: pin.Model, where: str) -> tuple[int, str]:
    need = DATA_BYTES_PER_NV3 * model.nv ** 3
    return need, (f"{where}: the model has nv = {model.nv} degrees of freedom and Pinocchio 4.1's Data allocates "
                  f"four nv x nv x nv tensors, {need / 2 ** 30:.3g} GiB (twice that while it is built)")


def data_limit() -> tuple[int | None, str]:
    """The most one Pinocchio Data may take [bytes] and what sets it: $MOREAU_SIM_DATA_LIMIT_GB [GiB]
    if set, else the memory available (available_memory; None if unknown). Refusing by this estimate
    comes before the allocation because Linux overcommits: a Data over the free memory is often not
    a MemoryError but pages touched later and the process killed by the OOM killer."""
    text = os.environ.get(DATA_LIMIT_VARIABLE)
    if text:
        try:
            gib = float(text)
        except ValueError:
            raise SceneError(f"${DATA_LIMIT_VARIABLE} = {text!r}: a number of GiB expected") from None
        return int(gib * 2 ** 30), f"the limit ${DATA_LIMIT_VARIABLE} = {text} GiB"
    avail = available_memory()
    return avail, "" if avail is None else (f"the {avail / 2 ** 30:.3g} GiB of memory available "
                                            f"(${DATA_LIMIT_VARIABLE} sets another limit)")


def check_data_size(model: pin.Model, where: str) -> None:
    """A SceneError naming `where`, nv and the size when one Data of `model` would exceed data_limit() at
    its peak (DATA_PEAK times its tensors):
    Pinocchio 4.1 allocates DATA_BYTES_PER_NV3 * nv^3 bytes in every Data whatever algorithms run
    (upstream stack-of-tasks/pinocchio#2949), 32 GB at nv = 1000."""
    need, msg = _data_message(model, where)
    limit, what = data_limit()
    if limit is not None and DATA_PEAK * need > limit:
        raise SceneError(f"{msg}, more than {what}")


def new_data(model: pin.Model, where: str, *, checked: bool = False) -> pin.Data:
    """A new Data of `model` (``pin.Data(model)``: ``model.createData()``'s, without the copy its binding returns, half
    the cost) after check_data_size (unless `checked`: a larger model's passed), or a
    SceneError naming `where` and the size when the allocation fails all the same (MemoryError, or
    std::bad_alloc as a RuntimeError)."""
    if not checked:
        check_data_size(model, where)
    try:
        return pin.Data(model)
    except MemoryError:
        pass
    except RuntimeError as exc:
        if "alloc" not in str(exc):
            raise
    raise SceneError(f"{_data_message(model, where)[1]}, which could not be allocated") from None
