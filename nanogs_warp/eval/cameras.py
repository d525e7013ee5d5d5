"""Pinhole cameras for evaluation: orbits derived from a scene alone, or the INRIA trainer's cameras.json.

Axes are OpenCV/COLMAP's (x right, y down, z forward): a world point p is at ``R p + t`` in the
camera frame. ``(cx, cy)`` is the principal point in continuous image coordinates, where pixel
(px, py) covers [px, px + 1) x [py, py + 1) and is sampled at its centre (see ``kernels/render.py``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.common import read_file_bytes
from ..splats import SplatSet

NEAR = 0.2  # INRIA's near plane, in world units
# Image sizes eval renders: at least the SSIM window (11 pixels) a side; at most 8192 a side and
# 2^28 pixels over all views (3 GB of float32 RGB for the reference's images, as much again per test).
MIN_SIDE = 11
MAX_SIDE = 8192
MAX_PIXELS = 1 << 28
MAX_VIEWS = 4096
NEAR_FRACTION = 0.1  # of the distance cameras keep from a scene's centre (``near_plane``)

UP_AXES = {
    "+x": (1.0, 0.0, 0.0),
    "-x": (-1.0, 0.0, 0.0),
    "+y": (0.0, 1.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "+z": (0.0, 0.0, 1.0),
    "-z": (0.0, 0.0, -1.0),
}


@dataclass
class Camera:
    """A pinhole camera: world-to-camera ``rotation`` (3x3) and ``translation`` (3,), focal lengths and
    principal point in pixels, image size, a name for the images written of its view and the near
    plane: splats at a view-space depth of ``near`` or less are culled (INRIA's 0.2 by default)."""

    rotation: np.ndarray
    translation: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    name: str = ""
    near: float = NEAR

    @property
    def centre(self) -> np.ndarray:
        """The camera centre in world space, -R^T t."""
        return -np.asarray(self.rotation, np.float64).T @ np.asarray(self.translation, np.float64)

    @staticmethod
    def look_at(position, target, up, fx, fy, width, height, name="", near=NEAR) -> Camera:
        """A camera at ``position`` looking at ``target`` whose image up is as close to ``up`` as can be,
        culling at ``near``."""
        position = np.asarray(position, np.float64)
        forward = np.asarray(target, np.float64) - position
        norm = np.linalg.norm(forward)
        if norm == 0:
            raise ValueError("camera position and target coincide")
        forward /= norm
        up = np.asarray(up, np.float64)
        right = np.cross(forward, up)
        if np.linalg.norm(right) < 1e-6 * np.linalg.norm(up):  # looking along the up axis
            helper = np.eye(3)[np.argmin(np.abs(forward))]
            right = np.cross(forward, helper)
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rotation = np.stack([right, down, forward])
        return Camera(rotation, -rotation @ position, fx, fy, width / 2.0, height / 2.0, width, height, name, near)


def near_plane(distance: float) -> float:
    """The near plane of cameras ``distance`` from a scene's centre: INRIA's 0.2, or a tenth of the
    distance where that is less. A scene stored in small units (a 5 cm object in metres) would
    otherwise lie inside the near plane and be culled whole; with it, its views do not depend on its
    units."""
    return min(NEAR, NEAR_FRACTION * float(distance))


def parse_up(up: str) -> np.ndarray:
    """``+x``, ``-x``, ``+y``, ``-y``, ``+z`` or ``-z`` (``x`` means ``+x``) as a unit vector."""
    key = up.strip().lower()
    if key in ("x", "y", "z"):
        key = "+" + key
    if key not in UP_AXES:
        raise InputError(f"--up {up!r}: expected one of {', '.join(UP_AXES)}")
    return np.array(UP_AXES[key])


def scene_frame(means: np.ndarray) -> tuple[np.ndarray, float]:
    """The robust centre of a scene (coordinate-wise median of the splat centres) and the orbit radius,
    2.2 x the 90th percentile of the centres' distances from it (1.0 when that is 0)."""
    means = np.asarray(means, np.float64).reshape(-1, 3)
    means = means[np.isfinite(means).all(axis=1)]
    if len(means) == 0:
        raise InputError("the reference scene has no splat with a finite centre to place cameras around")
    centre = np.median(means, axis=0)
    spread = float(np.percentile(np.linalg.norm(means - centre, axis=1), 90))
    return centre, 2.2 * spread if spread > 0 else 1.0


def check_side(size: int) -> None:
    """Refuses an image side outside [MIN_SIDE, MAX_SIDE] (``--size``)."""
    if not MIN_SIDE <= size <= MAX_SIDE:
        raise InputError(f"--size {size}: must be {MIN_SIDE} to {MAX_SIDE} pixels (SSIM needs {MIN_SIDE} a side)")


def check_pixels(total: int) -> None:
    """Refuses renders of more than MAX_PIXELS pixels over all views."""
    if total > MAX_PIXELS:
        raise InputError(f"{total:,} pixels over all views is more than the {MAX_PIXELS:,} eval renders; use fewer or smaller views")


def fibonacci_directions(count: int, up: np.ndarray) -> np.ndarray:
    """``count`` unit vectors spread evenly on the sphere (Fibonacci lattice), the first near ``up``."""
    i = np.arange(count, dtype=np.float64) + 0.5
    height = 1.0 - 2.0 * i / count
    ring = np.sqrt(np.maximum(0.0, 1.0 - height * height))
    angle = math.pi * (3.0 - math.sqrt(5.0)) * np.arange(count)
    local = np.stack([ring * np.cos(angle), ring * np.sin(angle), height], axis=1)
    pole = np.asarray(up, np.float64) / np.linalg.norm(up)
    a = np.eye(3)[np.argmin(np.abs(pole))]
    e1 = np.cross(pole, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(pole, e1)
    return local[:, :1] * e1 + local[:, 1:2] * e2 + local[:, 2:] * pole


def orbit_cameras(
    splats: SplatSet | np.ndarray, views: int = 16, size: int = 256, up: str = "-y", fov_y_deg: float = 60.0
) -> list[Camera]:
    """``views`` square ``size`` x ``size`` cameras on a Fibonacci sphere around the scene's robust centre,
    at 2.2 x the 90th-percentile centre distance, looking at the centre with ``fov_y_deg`` vertical field
    of view and world ``up`` (default -y, as INRIA/COLMAP scenes are y-down) at the top of the image.

    The near plane is ``near_plane(radius)``: INRIA's 0.2, less around scenes stored in small units.

    ``splats`` is a SplatSet or an (N, 3) array of centres. Derive the cameras from the reference scene
    only, so that every scene compared is seen by identical cameras.
    """
    if not 1 <= views <= MAX_VIEWS:
        raise InputError(f"--views {views}: need 1 to {MAX_VIEWS} views")
    check_side(size)
    check_pixels(views * size * size)
    if not 0.0 < fov_y_deg < 180.0:
        raise InputError(f"field of view {fov_y_deg} degrees: expected (0, 180)")
    up_vector = parse_up(up)
    means = splats.means.numpy() if isinstance(splats, SplatSet) else splats
    centre, radius = scene_frame(means)
    focal = 0.5 * size / math.tan(math.radians(fov_y_deg) / 2.0)
    directions = fibonacci_directions(views, up_vector)
    near = near_plane(radius)
    return [
        Camera.look_at(centre + radius * d, centre, up_vector, focal, focal, size, size, f"view_{k:03d}", near)
        for k, d in enumerate(directions)
    ]


MAX_DECLARED_SIDE = 1 << 31  # a camera's own image side, before --size scales it


def load_cameras_json(path: Path | str, size: int | None = None) -> list[Camera]:
    """Cameras from the ``cameras.json`` the INRIA trainer writes: a list of {id, img_name, width,
    height, position, rotation (3x3 camera-to-world, rows), fx, fy}, principal point at the image
    centre. An entry may also give ``near``, its near plane in world units (INRIA's 0.2 otherwise):
    cameras made for a scene in small units need a nearer one. With ``size``, each camera is
    rescaled so that its longer side is ``size`` pixels."""
    path = Path(path)
    try:
        entries = json.loads(read_file_bytes(path).decode("utf-8"))
    except InputError as e:
        raise InputError(f"cannot read cameras {path}: {str(e).split(': ', 1)[-1]}") from None
    except ValueError as e:  # not UTF-8, not JSON, or an integer too long to read
        raise InputError(f"cameras {path} is not JSON: {e}") from None
    except RecursionError:
        raise InputError(f"cameras {path}: nested too deeply to be a list of cameras") from None
    if not isinstance(entries, list) or not entries:
        raise InputError(f"cameras {path}: expected a non-empty JSON list of cameras")
    if size is not None:
        check_side(size)
    if len(entries) > MAX_VIEWS * 16:
        raise InputError(f"cameras {path}: {len(entries):,} cameras; eval renders at most {MAX_VIEWS * 16:,}")
    cameras = []
    limit = float(np.finfo(np.float32).max)
    for k, entry in enumerate(entries):
        try:
            width, height = _whole(entry["width"]), _whole(entry["height"])
            fx, fy = float(entry["fx"]), float(entry["fy"])
            position = np.asarray(entry["position"], np.float64).reshape(3)
            c2w = np.asarray(entry["rotation"], np.float64).reshape(3, 3)
            name = str(entry.get("img_name", entry.get("id", k)))
            near = float(entry.get("near", NEAR))
        except (KeyError, TypeError, ValueError, OverflowError) as e:
            raise InputError(f"cameras {path}: camera {k} is malformed ({type(e).__name__}: {e})") from None
        if not 0 < near < limit:
            raise InputError(f"cameras {path}: camera {k}'s near plane must be a positive number of world units, got {near}")
        if width < 1 or height < 1 or not (0 < fx < limit and 0 < fy < limit) or not np.isfinite(np.r_[position, c2w.ravel()]).all():
            raise InputError(f"cameras {path}: camera {k} has a non-positive size or focal length or a non-finite pose")
        if np.abs(position).max() >= limit or np.abs(c2w @ c2w.T - np.eye(3)).max() > 1e-3 or np.linalg.det(c2w) < 0:
            raise InputError(f"cameras {path}: camera {k}'s rotation is not a rotation or its position is beyond float32")
        if max(width, height) > MAX_DECLARED_SIDE:  # beyond any image; and width * scale would overflow a float
            raise InputError(f"cameras {path}: camera {k} declares {width} x {height} pixels, beyond {MAX_DECLARED_SIDE:,} a side")
        if size is not None:
            scale = size / max(width, height)
            new_w, new_h = max(1, round(width * scale)), max(1, round(height * scale))
            fx, fy = fx * new_w / width, fy * new_h / height
            width, height = new_w, new_h
        if not (MIN_SIDE <= min(width, height) and max(width, height) <= MAX_SIDE):
            raise InputError(f"cameras {path}: camera {k} renders {width} x {height} pixels; eval needs {MIN_SIDE} to "
                             f"{MAX_SIDE} a side (--size sets the longer side)")  # fmt: skip
        rotation = c2w.T
        cameras.append(Camera(rotation, -rotation @ position, fx, fy, width / 2.0, height / 2.0, width, height, name, near))
    check_pixels(sum(c.width * c.height for c in cameras))
    return cameras


def _whole(value) -> int:
    """An image size from JSON: a whole number (not a boolean)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (isinstance(value, float) and not value.is_integer()):
        raise ValueError(f"{value!r} is not a whole number of pixels")
    return int(value)
