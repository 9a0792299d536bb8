"""Browser replay of a trajectory NPZ, drawn by viser (docs/viewer.md): the model rebuilt from the
NPZ (stored), the meshes drawn (meshes, parts), the camera, the page (replay, overlay) and its
file or server (server)."""

from . import overlay
from .camera import FILL as camera_fill, FOV as camera_fov, camera
from .meshes import MESH_SUFFIXES, ground_box, shape_mesh
from .parts import Part, drawable_geometry, frames, parts, rods
from .replay import DEFAULT_FPS, contacts_per_frame, frame_indices, initial_camera, page
from .server import export_html, make_server, serve, url_of
from .stored import check_named_files, model_from_trajectory

__all__ = ["DEFAULT_FPS", "MESH_SUFFIXES", "Part", "camera", "camera_fill", "camera_fov", "check_named_files",
           "contacts_per_frame", "drawable_geometry", "export_html", "frame_indices", "frames", "ground_box",
           "initial_camera", "make_server", "model_from_trajectory", "overlay", "page", "parts", "rods", "serve",
           "shape_mesh", "url_of"]
