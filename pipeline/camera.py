"""Pinhole cameras and the one view-space convention every stage uses.

View space is right-handed: +X right, +Y up, the camera looks down -Z. Depth maps store the
positive distance along -Z (``d = -z_view``, metres) and 0 where there is no fluid. Normals are
unit view-space vectors; a surface facing the camera has n_z > 0. Pixel (col i, row j) has its
centre at (i + 0.5, j + 0.5), row 0 at the top.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.config import Cameras
from pipeline.particles import Z_UP_TO_Y_UP
from pipeline.vectors import is_tensor


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World-to-view 4x4 matrix of a camera at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        right = np.cross(forward, (0.0, 0.0, 1.0))
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, true_up, -forward
    view[:3, 3] = -view[:3, :3] @ eye
    return view


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: world-to-view matrix, vertical field of view and image size."""

    view: np.ndarray
    fov_y_deg: float
    width: int
    height: int

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (same horizontally and vertically: square pixels)."""
        return 0.5 * self.height / math.tan(math.radians(self.fov_y_deg) / 2.0)

    @property
    def eye(self) -> np.ndarray:
        """Camera position in world space."""
        return -self.view[:3, :3].T @ self.view[:3, 3]

    @property
    def cam_to_world(self) -> np.ndarray:
        """View-to-world 4x4 matrix (the pose pyrender wants)."""
        return np.linalg.inv(self.view)

    def to_view(self, points: np.ndarray) -> np.ndarray:
        """World points (N x 3) to view space (a torch tensor: in its dtype, on its device)."""
        rotation, offset = self.view[:3, :3].T, self.view[:3, 3]
        if is_tensor(points):
            import torch

            rotation, offset = (torch.as_tensor(a, dtype=points.dtype, device=points.device)
                                for a in (rotation, offset))
        return points @ rotation + offset

    def project(self, points_view: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """View points to (column, row, depth) in pixels and metres."""
        d = -points_view[:, 2]
        f = self.focal_px
        col = self.width / 2.0 + f * points_view[:, 0] / d
        row = self.height / 2.0 - f * points_view[:, 1] / d
        return col, row, d

    def pixel_rays(self) -> np.ndarray:
        """Per-pixel view-space ray directions scaled so that z = -1 (H x W x 3)."""
        f = self.focal_px
        cols = (np.arange(self.width) + 0.5 - self.width / 2.0) / f
        rows = -(np.arange(self.height) + 0.5 - self.height / 2.0) / f
        x, y = np.meshgrid(cols, rows)
        return np.stack([x, y, -np.ones_like(x)], axis=-1).astype(np.float32)

    def unproject(self, depth: np.ndarray) -> np.ndarray:
        """View-space positions (H x W x 3) of a depth map (positive depth along -Z)."""
        return self.pixel_rays() * depth[..., None]


def camera_for_frame(cameras: Cameras, path: str, index: int, count: int, width: int, height: int) -> Camera:
    """The camera of ``path`` ('static' or 'orbit') at frame ``index`` of ``count`` (0-based)."""
    if path == "static":
        c = cameras.static
        return Camera(look_at(c.eye, c.target), c.fov_deg, width, height)
    if path == "orbit":
        c = cameras.orbit
        t = index / max(count - 1, 1)
        azimuth = math.radians(c.start_deg + c.sweep_deg * t)
        target = np.asarray(c.target, float)
        eye = target + np.array([c.distance * math.sin(azimuth), c.height, c.distance * math.cos(azimuth)])
        return Camera(look_at(eye, target), c.fov_deg, width, height)
    raise ValueError(f"unknown camera path {path!r} (static or orbit)")


def camera_from_pose(cam_to_world: np.ndarray, focal_mm: float, sensor_width_mm: float, width: int,
                     height: int) -> Camera:
    """A camera from a 3D package's pose (camera-to-world 4x4, looking down -Z with +Y up) and lens.

    The sensor width spans the image's longer side (Blender's automatic sensor fit)."""
    tan_long = 0.5 * sensor_width_mm / focal_mm
    tan_y = tan_long if height >= width else tan_long * height / width
    return Camera(np.linalg.inv(np.asarray(cam_to_world, np.float64)), math.degrees(2 * math.atan(tan_y)), width,
                  height)


def lens_of(camera: Camera, sensor_width_mm: float = 36.0) -> float:
    """The focal length (mm) that gives ``camera`` its field of view on a sensor this wide."""
    tan_y = math.tan(math.radians(camera.fov_y_deg) / 2)
    tan_long = tan_y if camera.height >= camera.width else tan_y * camera.width / camera.height
    return 0.5 * sensor_width_mm / tan_long


def framing_cameras(lo, hi, width: int, height: int, count: int, orbit: bool = False, fov_deg: float = 40.0,
                    elevation_deg: float = 20.0, azimuth_deg: float = 30.0, margin: float = 0.05) -> list[Camera]:
    """``count`` cameras that keep the box ``lo``..``hi`` (Y up) in view from ``elevation_deg``, all
    at ``azimuth_deg`` or, with ``orbit``, circling the box once over the sequence; each as close as
    keeps the box's corners ``margin`` (a share of the image) inside the frame, at one distance."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre, reach = 0.5 * (lo + hi), max(0.5 * float(np.linalg.norm(hi - lo)), 1e-9)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    el = math.radians(elevation_deg)
    azimuths = [math.radians(azimuth_deg + (360.0 * i / count if orbit else 0.0)) for i in range(count)]

    def camera(az: float, distance: float) -> Camera:
        eye = centre + distance * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        return Camera(look_at(eye, centre), fov_deg, width, height)

    def fits(az: float, distance: float) -> bool:
        cam = camera(az, distance)
        col, row, depth = cam.project(cam.to_view(corners))
        mx, my = margin * width, margin * height
        inside = (col >= mx) & (col <= width - mx) & (row >= my) & (row <= height - my)
        return bool(np.all(depth > 0) and np.all(inside))

    def closest(az: float) -> float:
        near, far = reach, 2.0 * reach
        while not fits(az, far):
            far *= 2.0
        for _ in range(40):  # bisection: the fitting distances are one interval [d*, inf)
            mid = 0.5 * (near + far)
            near, far = (near, mid) if fits(az, mid) else (mid, far)
        return far

    distance = max(closest(az) for az in azimuths)
    return [camera(az, distance) for az in azimuths]


def random_view(positions: np.ndarray, radius: float, rng: np.random.Generator, radius_px: tuple[float, float],
                size: tuple[int, int], fov_deg: tuple[float, float], elevation_deg: tuple[float, float],
                tries: int = 32) -> Camera:
    """A random camera for training views: it looks at a random particle from a random azimuth and
    elevation with a random field of view and a square image side in ``size`` (a multiple of 32),
    from the distance at which that particle's radius projects to a log-uniform draw from
    ``radius_px`` pixels. Side and projected radius are drawn together so that the frame, scaled to
    3 px per radius, keeps at least about 128 px (``pipeline.model.scale``). Eyes closer than four
    radii to a particle (inside the fluid) are drawn again, up to ``tries`` times."""
    pts = np.asarray(positions, np.float64)
    cam = None
    for _ in range(tries):
        r_px = float(np.exp(rng.uniform(np.log(radius_px[0]), np.log(radius_px[1]))))
        lo = max(size[0], min(size[1], int(np.ceil(43.0 * r_px))))
        side = int(round(rng.uniform(lo, size[1]) / 32.0)) * 32
        fov = float(rng.uniform(*fov_deg))
        focal = 0.5 * side / math.tan(math.radians(fov) / 2.0)
        distance = focal * radius / r_px
        target = pts[int(rng.integers(len(pts)))] if len(pts) else np.zeros(3)
        az, el = rng.uniform(0.0, 2.0 * math.pi), math.radians(float(rng.uniform(*elevation_deg)))
        eye = target + distance * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        cam = Camera(look_at(eye, target), fov, side, side)
        if not len(pts) or float(np.min(np.sum((pts - eye) ** 2, axis=1))) > (4.0 * radius) ** 2:
            return cam
    return cam


def _to_y_up(up: str) -> np.ndarray:
    """4x4 rotation from a world with ``up`` ('y' or 'z') to the pipeline's Y-up world."""
    out = np.eye(4)
    if up == "z":
        out[:3, :3] = Z_UP_TO_Y_UP
    elif up != "y":
        raise ValueError(f"up must be 'y' or 'z', got {up!r}")
    return out


def read_camera_file(path: Path, frames: list[int], width: int, height: int) -> list[Camera]:
    """The cameras of ``frames`` from a camera JSON (``write_camera_file``'s format; the README shows
    a Blender script that exports one): one entry per frame number, or a single entry for all."""

    path = Path(path)
    try:
        data = _camera_json(path)
        up = data.get("up", "y")
        rotate = _to_y_up(up)
        if not isinstance(data["frames"], list) or not all(isinstance(e, dict) for e in data["frames"]):
            raise ValueError("'frames' must be a list of objects, one per frame")
        entries = {int(e["frame"]) if "frame" in e else None: e for e in data["frames"]}
        if not entries:
            raise ValueError("it lists no frames")
        single = next(iter(entries.values())) if len(entries) == 1 else None
        missing = [f for f in frames if f not in entries and single is None]
        if missing:
            raise ValueError(f"no camera for frames {missing[:5]}{' ...' if len(missing) > 5 else ''}")
        cameras = []
        for f in frames:
            e = entries.get(f, single)
            pose = np.asarray(e["camera_to_world"], np.float64)
            if pose.shape != (4, 4) or not np.isfinite(pose).all():
                raise ValueError(f"frame {f}: camera_to_world must be a finite 4x4 matrix")
            if abs(np.linalg.det(pose[:3, :3])) < 1e-9:
                raise ValueError(f"frame {f}: camera_to_world's rotation is singular (it maps space onto a plane)")
            lens = {k: float(e.get(k, 36.0 if k == "sensor_width_mm" else float("nan")))
                    for k in ("focal_length_mm", "sensor_width_mm")}
            for key, value in lens.items():
                if not (math.isfinite(value) and value > 0):
                    raise ValueError(f"frame {f}: {key} must be > 0, got {e.get(key)!r}")
            cameras.append(camera_from_pose(rotate @ pose, lens["focal_length_mm"], lens["sensor_width_mm"],
                                            width, height))
        return cameras
    except FileNotFoundError:
        raise FileNotFoundError(f"camera file {path} not found") from None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        message = f"missing key {exc}" if isinstance(exc, KeyError) else str(exc)
        raise ValueError(f"camera file {path}: {message}") from None


def _camera_json(path: Path) -> dict:
    """A camera file's JSON object (``write_camera_file``'s format)."""
    import json

    data = json.loads(path.read_text(encoding="utf-8"))
    if not isinstance(data, dict):
        raise ValueError(f"must be a JSON object with a 'frames' list (the format of a render's camera.json), "
                         f"not a {type(data).__name__}")
    return data


def camera_file_size(path: Path) -> tuple[int, int] | None:
    """The image width and height a camera file records (None when it records none)."""
    try:
        data = _camera_json(Path(path))
    except (ValueError, OSError) as exc:
        raise ValueError(f"camera file {path}: {exc}") from None
    width, height = data.get("width"), data.get("height")
    if isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0:
        return width, height
    return None


def write_camera_file(path: Path, cameras: list[Camera], frames: list[int], up: str = "y",
                      sensor_width_mm: float = 36.0) -> None:
    """Per-frame camera-to-world matrices (in the world whose up axis is ``up``), focal length and
    sensor width as JSON, so a 3D package can match the rendered frames."""
    import json

    from pipeline.cache import atomic_path

    back = np.linalg.inv(_to_y_up(up))
    entries = [{"frame": int(f), "camera_to_world": (back @ c.cam_to_world).round(9).tolist(),
                "focal_length_mm": round(lens_of(c, sensor_width_mm), 6), "sensor_width_mm": sensor_width_mm}
               for f, c in zip(frames, cameras, strict=True)]
    body = {"format": "deep-ssfr camera 1", "up": up, "width": cameras[0].width if cameras else 0,
            "height": cameras[0].height if cameras else 0, "frames": entries}
    with atomic_path(Path(path)) as tmp:
        tmp.write_text(json.dumps(body, indent=1))


def sequence_cameras(choice: str, frames: list[int], lo, hi, width: int, height: int) -> tuple[list[Camera], dict]:
    """The camera of every frame for ``choice`` ('auto': framing the box ``lo``..``hi``, 'orbit':
    circling it, else a camera JSON path), and the plain data that identifies them (a cache key)."""
    if choice in ("auto", "orbit"):
        cams = framing_cameras(lo, hi, width, height, len(frames), orbit=choice == "orbit")
        return cams, {"kind": choice, "lo": [float(v) for v in lo], "hi": [float(v) for v in hi]}
    cams = read_camera_file(Path(choice), frames, width, height)
    return cams, {"kind": "file", "views": [c.view.round(9).tolist() for c in cams],
                  "fov": [c.fov_y_deg for c in cams]}
