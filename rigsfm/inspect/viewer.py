"""``rigsfm view OUT``: the network in Open3D — points, wide and narrow frustums, rig links, metric axes.

Wide frustums are blue, narrow ones orange (and twice as deep); a green line joins a rig's wide and narrow centres
(a point at the usual centimetre baselines); the world axes at the cameras' centroid are red x, green y, blue z.

``--screenshot FILE.png`` renders the same view headless with Open3D's OffscreenRenderer (Filament; on a
machine without GPU it needs a software Vulkan driver, Debian's mesa-vulkan-drivers); the engine's start lines
go to the log, not the terminal (:func:`engine_lines_to_log`). Where that is
impossible the same geometry is drawn by a small numpy/OpenCV rasteriser (lines and points, no shading)
and the fallback is logged.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import logging
import os
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pycolmap

from rigsfm.core.conventions import opencv_from_colmap_pixels
from rigsfm.core.errors import InputError, WorkspaceError
from rigsfm.core.names import name_of
from rigsfm.core.workspace import Workspace

logger = logging.getLogger(__name__)

WIDE_RGB = (0.0, 0.35, 1.0)
NARROW_RGB = (1.0, 0.45, 0.0)
LINK_RGB = (0.0, 0.7, 0.2)
BACKGROUND_RGB = (1.0, 1.0, 1.0)


@dataclass
class Scene:
    points: o3d.geometry.PointCloud
    lines: dict[str, o3d.geometry.LineSet]  # wide_frustums, narrow_frustums, rig_links, axes
    centre: np.ndarray
    size: float  # metres (or model units) spanned by the cameras
    up: np.ndarray


def pinhole_intrinsic(camera: pycolmap.Camera) -> o3d.camera.PinholeCameraIntrinsic:
    """Open3D intrinsics (OpenCV pixel centres, pinhole part only: distortion is dropped)."""
    cx, cy = opencv_from_colmap_pixels(np.array([camera.principal_point_x, camera.principal_point_y]))
    return o3d.camera.PinholeCameraIntrinsic(int(camera.width), int(camera.height), float(camera.focal_length_x),
                                             float(camera.focal_length_y), float(cx), float(cy))


def frustum(camera: pycolmap.Camera, cam_from_world: pycolmap.Rigid3d, depth: float) -> o3d.geometry.LineSet:
    """The camera's pyramid to ``depth``: its centre, the image corners and their rectangle (8 lines)."""
    intrinsic = pinhole_intrinsic(camera)
    extrinsic = np.vstack([cam_from_world.matrix(), [0, 0, 0, 1]])
    full = o3d.geometry.LineSet.create_camera_visualization(intrinsic, extrinsic, scale=depth)
    # Open3D adds the camera's own x, y, z axes, each `depth` long: painted in the frustum's colour they were long
    # lines sticking out of every camera that nothing explained
    return o3d.geometry.LineSet(full.points, o3d.utility.Vector2iVector(np.asarray(full.lines)[:8]))


def _merge(line_sets: list[o3d.geometry.LineSet], colour) -> o3d.geometry.LineSet:
    merged = o3d.geometry.LineSet()
    for line_set in line_sets:
        merged += line_set
    merged.paint_uniform_color(colour)
    return merged


def build_scene(reconstruction: pycolmap.Reconstruction) -> Scene:
    images = [im for im in reconstruction.images.values() if im.has_pose]
    if not images:
        raise WorkspaceError("the model has no registered images to show")
    centres = np.array([im.projection_center() for im in images])
    size = float(np.ptp(centres, axis=0).max()) or 1.0
    wide: list = []
    narrow: list = []
    for image in images:
        is_narrow = name_of(image).is_narrow
        camera = reconstruction.cameras[image.camera_id]
        (narrow if is_narrow else wide).append(frustum(camera, image.cam_from_world(), (0.25 if is_narrow else 0.12) * size))
    by_rig: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    for image, centre in zip(images, centres):
        name = name_of(image)
        by_rig.setdefault((name.rig, name.frame), {})[name.sensor] = centre
    ends = [(v["wide"], v["narrow"]) for v in by_rig.values() if {"wide", "narrow"} <= set(v)]
    links = o3d.geometry.LineSet(o3d.utility.Vector3dVector(np.array([p for e in ends for p in e]).reshape(-1, 3)),
                                 o3d.utility.Vector2iVector(np.arange(2 * len(ends)).reshape(-1, 2)))
    links.paint_uniform_color(LINK_RGB)
    up = np.mean([-im.cam_from_world().rotation.matrix()[1] for im in images], axis=0)
    up /= max(np.linalg.norm(up), 1e-12)
    axis_length = 10 ** np.floor(np.log10(size))  # a round number of metres, 10-100 % of the network
    origin = centres.mean(axis=0)
    axes = o3d.geometry.LineSet(
        o3d.utility.Vector3dVector(np.array([origin, origin + [axis_length, 0, 0], origin, origin + [0, axis_length, 0],
                                             origin, origin + [0, 0, axis_length]])),
        o3d.utility.Vector2iVector(np.array([[0, 1], [2, 3], [4, 5]])))
    axes.colors = o3d.utility.Vector3dVector(np.eye(3))
    points = o3d.geometry.PointCloud()
    if reconstruction.num_points3D():
        points.points = o3d.utility.Vector3dVector(np.array([p.xyz for p in reconstruction.points3D.values()]))
        points.colors = o3d.utility.Vector3dVector(
            np.array([p.color for p in reconstruction.points3D.values()], dtype=np.float64) / 255.0)
    return Scene(points, {"wide_frustums": _merge(wide, WIDE_RGB), "narrow_frustums": _merge(narrow, NARROW_RGB),
                          "rig_links": links, "axes": axes}, origin, size, up)


def view_eye(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """A camera above and behind the network looking at its centre: (eye, look-at)."""
    cloud = np.asarray(scene.points.points)
    target = 0.5 * (np.median(cloud, axis=0) + scene.centre) if len(cloud) else scene.centre
    horizontal = scene.centre - target - np.dot(scene.centre - target, scene.up) * scene.up
    if np.linalg.norm(horizontal) < 1e-9:
        horizontal = np.cross(scene.up, [1.0, 0.0, 0.0] if abs(scene.up[0]) < 0.9 else [0.0, 1.0, 0.0])
    horizontal /= np.linalg.norm(horizontal)
    reach = max(scene.size, 2.0 * np.linalg.norm(scene.centre - target))
    eye = target + (0.6 * horizontal + 1.0 * scene.up) * 1.3 * reach
    return eye, target


def linear_from_srgb(colour) -> np.ndarray:
    """Filament takes linear colours and writes sRGB: convert so that the PNG shows the intended colours."""
    c = np.asarray(colour, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


@contextlib.contextmanager
def engine_lines_to_log() -> Iterator[list[str]]:
    """Open3D's and Filament's engine lines ('[Open3D INFO] EngineInstance: ...', 'FEngine ... created'), which
    native code writes to file descriptors 1 and 2, go to the log instead of the terminal: debug level, but lines
    that speak of an error at warning level. Open3D's own logger is set to errors meanwhile. The lines are handed
    out (filled when the block ends, also when it raises) so that a failed render can name them."""
    lines: list[str] = []
    level = o3d.utility.get_verbosity_level()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a stream pytest or a caller replaced may not flush
            stream.flush()
    libc = ctypes.CDLL(None)
    with tempfile.TemporaryFile() as sink:
        saved = (os.dup(1), os.dup(2))
        try:
            o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            yield lines
        finally:
            libc.fflush(None)  # C's stdio buffers what native code printed: out before the descriptors go back
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
            o3d.utility.set_verbosity_level(level)
            sink.seek(0)
            lines.extend(line.strip() for line in sink.read().decode(errors="replace").splitlines() if line.strip())
            for line in lines:
                logger.log(logging.WARNING if "error" in line.lower() else logging.DEBUG, "Open3D: %s", line)


def render_offscreen(scene: Scene, width: int, height: int) -> np.ndarray:
    with engine_lines_to_log():
        return _render_offscreen(scene, width, height)


def _render_offscreen(scene: Scene, width: int, height: int) -> np.ndarray:
    rendering = o3d.visualization.rendering
    renderer = rendering.OffscreenRenderer(width, height)
    renderer.scene.set_background([*BACKGROUND_RGB, 1.0])
    renderer.scene.view.set_color_grading(rendering.ColorGrading(rendering.ColorGrading.Quality.ULTRA,
                                                                 rendering.ColorGrading.ToneMapping.LINEAR))
    lines = rendering.MaterialRecord()
    lines.shader, lines.line_width = "unlitLine", 3.0
    dots = rendering.MaterialRecord()
    dots.shader, dots.point_size = "defaultUnlit", 2.0
    if len(scene.points.points):
        renderer.scene.add_geometry("points", scene.points, dots)
    for name, line_set in scene.lines.items():
        linear = o3d.geometry.LineSet(line_set)
        linear.colors = o3d.utility.Vector3dVector(linear_from_srgb(np.asarray(line_set.colors)))
        renderer.scene.add_geometry(name, linear, lines)
    eye, target = view_eye(scene)
    renderer.setup_camera(50.0, target, eye, scene.up)
    image = np.asarray(renderer.render_to_image())
    return cv2.cvtColor(image, cv2.COLOR_RGB2BGR)


def render_raster(scene: Scene, width: int, height: int) -> np.ndarray:
    """The same view drawn with OpenCV: a pinhole camera at ``view_eye``, lines and points only."""
    eye, target = view_eye(scene)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, scene.up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.array([right, down, forward])
    focal = 0.5 * height / np.tan(np.radians(25.0))

    def project(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cam = (np.asarray(xyz) - eye) @ rotation.T
        ok = cam[:, 2] > 1e-6
        return np.column_stack([focal * cam[:, 0] / cam[:, 2] + width / 2,
                                focal * cam[:, 1] / cam[:, 2] + height / 2]), ok

    canvas = np.full((height, width, 3), 255, np.uint8)
    xy, ok = project(np.asarray(scene.points.points)) if len(scene.points.points) else (np.zeros((0, 2)), [])
    colours: np.ndarray | list = (np.asarray(scene.points.colors)[:, ::-1] * 255).astype(int) if len(xy) else []
    for p, good, c in zip(xy, ok, colours):  # type: ignore[call-overload]  # project gives a mask
        if good and 0 <= p[0] < width and 0 <= p[1] < height:
            canvas[int(p[1]), int(p[0])] = c
    for line_set in scene.lines.values():
        xy, ok = project(np.asarray(line_set.points))
        colours = np.asarray(line_set.colors)
        for k, (a, b) in enumerate(np.asarray(line_set.lines)):
            if ok[a] and ok[b]:
                colour = tuple(int(255 * v) for v in colours[k][::-1])
                cv2.line(canvas, tuple(np.round(xy[a]).astype(int)), tuple(np.round(xy[b]).astype(int)), colour, 2,
                         cv2.LINE_AA)
    return canvas


def screenshot(out: Path, path: Path, width: int = 1280, height: int = 800, *, overwrite: bool = False) -> Path:
    """Render the network view headless into ``path`` (PNG; an existing file only with ``overwrite``); returns it."""
    path = Path(path)
    if not cv2.haveImageWriter(str(path)):  # checked before the work: OpenCV picks the format by the suffix
        raise InputError(f"--screenshot '{path}': no image format for the name's ending "
                         f"'{path.suffix}'; give a file name ending in .png (or .jpg)")
    if not overwrite and path.is_file():
        raise WorkspaceError(f"--screenshot '{path}' already exists: pass --overwrite to replace it")
    model = load_model(out)
    Workspace(Path(out)).refuse_among_images(path, f"--screenshot '{path}'", "write it outside that folder")
    scene = build_scene(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        image = render_offscreen(scene, width, height)
    except Exception as error:  # no GPU / Vulkan / EGL: draw the same geometry ourselves
        logger.warning("Open3D offscreen rendering unavailable (%s); using the OpenCV rasteriser", error)
        image = render_raster(scene, width, height)
    try:
        written = cv2.imwrite(str(path), image)
    except cv2.error:
        written = False
    if not written:  # imwrite says False (a folder of that name, no write permission, a full disk) but raises nothing
        raise WorkspaceError(f"cannot write the screenshot {path}: check that its folder is writable and that it is "
                             "not a folder itself")
    return path


def load_model(out: Path) -> pycolmap.Reconstruction:
    workspace = Workspace(Path(out))
    workspace.require_result()
    return workspace.read_sparse()


def _x11_display_opens(display: str) -> bool:
    """Whether libX11 connects to ``display``; True where libX11 is missing (then the window is simply tried)."""
    name = ctypes.util.find_library("X11")
    if name is None:
        return True
    try:
        x11 = ctypes.CDLL(name)
    except OSError:
        return True
    x11.XOpenDisplay.restype = ctypes.c_void_p
    x11.XOpenDisplay.argtypes = [ctypes.c_char_p]
    x11.XCloseDisplay.argtypes = [ctypes.c_void_p]
    connection = x11.XOpenDisplay(display.encode())
    if not connection:
        return False
    x11.XCloseDisplay(connection)
    return True


def _wayland_socket_exists(display: str) -> bool:
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    path = Path(display) if display.startswith("/") else Path(runtime or "/nonexistent", display)
    return path.is_socket()


def has_display() -> bool:
    """Whether a window can open here: an X11 display that accepts a connection or a Wayland socket. A DISPLAY
    that names no reachable server is not one: Open3D would then draw into an invisible offscreen window and wait
    on it for ever, deaf to Ctrl-C."""
    wayland, x11 = os.environ.get("WAYLAND_DISPLAY"), os.environ.get("DISPLAY")
    return bool((wayland and _wayland_socket_exists(wayland)) or (x11 and _x11_display_opens(x11)))


def show(out: Path) -> None:
    """Open an Open3D window on the network: points, wide (blue) and narrow (orange) frustums, rig links (green),
    world axes (red x, green y, blue z)."""
    if not has_display():
        which = ", ".join(f"{k}={os.environ[k]!r}" for k in ("DISPLAY", "WAYLAND_DISPLAY") if os.environ.get(k))
        why = (f"{which} names no display that accepts a connection" if which
               else "DISPLAY and WAYLAND_DISPLAY are unset")
        raise WorkspaceError(f"no display here ({why}): `rigsfm view` opens a window; use `rigsfm view OUT "
                             "--screenshot view.png` to render the view into a file instead")
    scene = build_scene(load_model(out))
    geometries = ([scene.points] if len(scene.points.points) else []) + list(scene.lines.values())
    try:
        o3d.visualization.draw_geometries(geometries, window_name=f"rigsfm: {out}", width=1280, height=800)
    except Exception as error:
        raise WorkspaceError(f"cannot open a window ({error}); use --screenshot FILE.png") from None
