"""The replay written as one HTML file, or served over HTTP from this machine (docs/viewer.md)."""

from __future__ import annotations

import http.server
import threading
import webbrowser
from pathlib import Path

from ..trajectory import Trajectory
from .replay import DEFAULT_FPS, page


def export_html(traj: Trajectory | str | Path, path: str | Path, *, fps: float = DEFAULT_FPS,
                colors: str = "link") -> Path:
    """Write the replay page to `path`: one file that opens from file:// without a server."""
    path = Path(path)
    text = page(traj, fps=fps, colors=colors)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


class _Handler(http.server.BaseHTTPRequestHandler):
    body: bytes = b""

    def do_GET(self):  # noqa: N802 (http.server's name)
        if self.path.split("?")[0].split("#")[0] not in ("/", "/index.html"):
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Type", "text/html; charset=utf-8")
        self.send_header("Content-Length", str(len(self.body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(self.body)

    def log_message(self, *args):  # quiet
        pass


def make_server(traj: Trajectory | str | Path, port: int = 0, host: str = "127.0.0.1", *,
                fps: float = DEFAULT_FPS, colors: str = "link") -> http.server.ThreadingHTTPServer:
    """An HTTP server (not yet serving) whose page is the replay; port 0 picks a free port
    (``server.server_address[1]``). Call ``serve_forever()`` and ``shutdown()``."""
    handler = type("ReplayHandler", (_Handler,), {"body": page(traj, fps=fps, colors=colors).encode("utf-8")})
    return http.server.ThreadingHTTPServer((host, port), handler)


def url_of(server: http.server.HTTPServer) -> str:
    host, port = server.server_address[:2]
    return f"http://{host if host not in ('', '0.0.0.0') else '127.0.0.1'}:{port}/"


def serve(traj: Trajectory | str | Path, port: int = 0, host: str = "127.0.0.1", *, open_browser: bool = True,
          fps: float = DEFAULT_FPS, colors: str = "link", ready=None) -> None:
    """Serve the replay until interrupted (Ctrl-C). `ready(url)` is called once it listens."""
    server = make_server(traj, port, host, fps=fps, colors=colors)
    url = url_of(server)
    try:
        if ready:
            ready(url)
        if open_browser:
            threading.Thread(target=webbrowser.open, args=(url,), daemon=True).start()
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
