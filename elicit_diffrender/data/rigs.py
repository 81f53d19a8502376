"""Camera rigs as Mitsuba 3 scene XML: generate, read, write and place them.

A rig file is a Mitsuba ``<scene>`` whose ``<sensor type="perspective" id="...">`` elements are the
cameras, so Mitsuba can render it directly. Shipped rigs (``scenes/``) live in a body-centred frame:
origin at the pelvis, +y up, the body facing +z. :func:`place_cameras` moves a rig onto a subject;
:func:`place_ring` places the ring around a subject's input pose.

Mitsuba's camera looks along +z with +x to the left and +y up; OpenCV's has +x right and +y down,
so ``to_world = inverse([R | T]) @ diag(-1, -1, 1, 1)``. The principal point maps to Mitsuba's
``principal_point_offset_{x,y} = -(c - size / 2) / size``.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..core.cameras import Camera, look_at
from ..core.errors import ElicitError
from ..core.io import write_text

if TYPE_CHECKING:
    from ..body import BodyModel
    from .subject import Subject

FLIP_XY = np.diag([-1.0, -1.0, 1.0, 1.0])
MAX_SIDE = 16384  # pixels on a film's side
SHIPPED_RIGS = ("input", "ring", "orbit")
RING_SIZE = 512  # image size of the shipped ring rig


class RigError(ElicitError):
    """A rig file or camera that cannot be read or expressed."""


def camera_to_world(camera: Camera) -> np.ndarray:
    """4x4 OpenCV camera-to-world transform."""
    m = np.eye(4)
    m[:3, :3] = camera.R.T
    m[:3, 3] = camera.center
    return m


def sensor_params(camera: Camera) -> dict:
    """Mitsuba perspective-sensor parameters that reproduce an OpenCV camera."""
    K = camera.K
    if abs(K[0, 1]) > 1e-9 or abs(K[1, 0]) > 1e-9 or abs(K[2, 0]) > 1e-9 or abs(K[2, 1]) > 1e-9:
        raise RigError(f"camera {camera.name!r}: skewed intrinsics cannot be expressed in Mitsuba")
    if abs(K[0, 0] - K[1, 1]) > 1e-6 * K[0, 0]:
        raise RigError(f"camera {camera.name!r}: fx != fy ({K[0, 0]} vs {K[1, 1]}); Mitsuba needs square pixels")
    return {
        "fov": math.degrees(2.0 * math.atan(camera.width / (2.0 * K[0, 0]))),
        "fov_axis": "x",
        "principal_point_offset_x": -(K[0, 2] - camera.width / 2.0) / camera.width,
        "principal_point_offset_y": -(K[1, 2] - camera.height / 2.0) / camera.height,
        "to_world": camera_to_world(camera) @ FLIP_XY,
    }


def _camera_from_sensor(
    fov: float, fov_axis: str, ppx: float, ppy: float, to_world: np.ndarray, width: int, height: int, name: str
) -> Camera:
    half = math.tan(math.radians(fov) / 2.0)
    span = {
        "x": width,
        "y": height,
        "smaller": min(width, height),
        "larger": max(width, height),
        "diagonal": math.hypot(width, height),
    }
    if fov_axis not in span:
        raise RigError(f"sensor {name!r}: unsupported fov_axis {fov_axis!r}")
    f = span[fov_axis] / (2.0 * half)
    K = np.array([[f, 0.0, width / 2.0 - ppx * width], [0.0, f, height / 2.0 - ppy * height], [0.0, 0.0, 1.0]])
    c2w = to_world @ FLIP_XY
    rot = c2w[:3, :3]
    scale = np.linalg.norm(rot, axis=0)
    if np.any(np.abs(scale - 1.0) > 1e-5):
        raise RigError(f"sensor {name!r}: to_world must be rigid (plus the x/y flip), got column norms {scale}")
    R = rot.T
    return Camera(K, R, -R @ c2w[:3, 3], width, height, name)


def _float(text: object, where: str) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise RigError(f"{where}: not a number: {text!r}") from None
    if not math.isfinite(value):
        raise RigError(f"{where}: not a finite number: {text!r}")
    return value


def _floats(text: str, n: int, where: str) -> np.ndarray:
    try:
        vals = np.array([float(v) for v in text.replace(",", " ").split()])
    except ValueError:
        raise RigError(f"{where}: not a list of numbers: {text!r}") from None
    if vals.size != n:
        raise RigError(f"{where}: expected {n} numbers, got {vals.size}")
    if not np.isfinite(vals).all():
        raise RigError(f"{where}: not finite: {text!r}")
    return vals


def _to_world(elem: ET.Element | None, where: str) -> np.ndarray:
    """Compose a Mitsuba ``<transform>`` (matrix, lookat, translate, scale) into a 4x4 matrix."""
    m = np.eye(4)
    if elem is None:
        return m
    for child in elem:
        if child.tag == "matrix":
            step = _floats(child.get("value", ""), 16, f"{where} <matrix>").reshape(4, 4)
        elif child.tag == "lookat":
            origin = _floats(child.get("origin", ""), 3, f"{where} <lookat origin>")
            target = _floats(child.get("target", ""), 3, f"{where} <lookat target>")
            up = _floats(child.get("up", "0 1 0"), 3, f"{where} <lookat up>")
            d = target - origin
            if np.linalg.norm(d) < 1e-9:
                raise RigError(f"{where} <lookat>: origin and target are the same point")
            d /= np.linalg.norm(d)
            left = np.cross(up, d)
            if np.linalg.norm(left) < 1e-9:
                raise RigError(f"{where} <lookat>: up is parallel to the viewing direction")
            left /= np.linalg.norm(left)
            new_up = np.cross(d, left)
            step = np.eye(4)
            step[:3, 0], step[:3, 1], step[:3, 2], step[:3, 3] = left, new_up, d, origin
        elif child.tag == "translate":
            step = np.eye(4)
            step[:3, 3] = [_float(child.get(k, 0.0), f"{where} <translate {k}>") for k in "xyz"]
        elif child.tag == "scale":
            if child.get("value") is not None:
                step = np.diag([_float(child.get("value"), f"{where} <scale value>")] * 3 + [1.0])
            else:
                step = np.diag([_float(child.get(k, 1.0), f"{where} <scale {k}>") for k in "xyz"] + [1.0])
        else:
            raise RigError(f"{where}: unsupported transform element <{child.tag}>")
        m = step @ m
    return m


def read_rig(path: str | Path) -> list[Camera]:
    """Cameras of every perspective sensor in a Mitsuba scene XML file, in file order."""
    path = Path(path)
    if not path.is_file():
        raise RigError(f"{path}: rig file not found")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise RigError(f"{path}: not valid XML ({exc})") from exc
    cameras = []
    for k, sensor in enumerate(root.iter("sensor")):
        name = sensor.get("id") or f"cam{k:02d}"
        where = f"{path} sensor {name!r}"
        if sensor.get("type") != "perspective":
            raise RigError(f"{where}: only perspective sensors are supported, got {sensor.get('type')!r}")
        props = {c.get("name"): c for c in sensor if c.get("name") is not None}
        film = sensor.find("film")
        if film is None:
            raise RigError(f"{where}: missing <film>")
        fprops = {c.get("name"): c.get("value") for c in film}
        try:
            width, height = int(fprops.get("width", 768)), int(fprops.get("height", 576))
            fov = float(props["fov"].get("value")) if "fov" in props else None
            if fov is None and "focal_length" in props:
                mm = float(props["focal_length"].get("value").rstrip("m"))
                fov = math.degrees(2 * math.atan(36.0 / (2 * mm)))
            fov_axis = props["fov_axis"].get("value") if "fov_axis" in props else "x"
            ppx = float(props["principal_point_offset_x"].get("value")) if "principal_point_offset_x" in props else 0
            ppy = float(props["principal_point_offset_y"].get("value")) if "principal_point_offset_y" in props else 0
        except (TypeError, ValueError, ZeroDivisionError) as exc:
            raise RigError(f"{where}: bad numeric property ({exc})") from None
        if fov is None:
            raise RigError(f"{where}: needs a 'fov' (or 'focal_length') property")
        if not (math.isfinite(fov) and 0.0 < fov < 180.0):
            raise RigError(f"{where}: fov must be between 0 and 180 degrees, got {fov!r}")
        if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE) or not (math.isfinite(ppx) and math.isfinite(ppy)):
            raise RigError(f"{where}: film {width}x{height} or principal point offset out of range")
        to_world = _to_world(sensor.find("transform[@name='to_world']"), where)
        cameras.append(_camera_from_sensor(fov, fov_axis, ppx, ppy, to_world, width, height, name))
    if not cameras:
        raise RigError(f"{path}: no <sensor> elements")
    return cameras


def rig_xml(cameras: list[Camera], comment: str = "") -> str:
    """Mitsuba scene XML text holding ``cameras`` as perspective sensors."""
    lines = ['<?xml version="1.0" encoding="utf-8"?>']
    if comment:
        lines.append(f"<!-- {comment} -->")
    lines.append('<scene version="3.0.0">')
    for cam in cameras:
        p = sensor_params(cam)
        matrix = " ".join(f"{v:.9g}" for v in p["to_world"].ravel())
        lines += [
            f'    <sensor type="perspective" id="{cam.name}">',
            f'        <float name="fov" value="{p["fov"]:.12g}"/>',
            f'        <string name="fov_axis" value="{p["fov_axis"]}"/>',
            f'        <float name="principal_point_offset_x" value="{p["principal_point_offset_x"] + 0.0:.12g}"/>',
            f'        <float name="principal_point_offset_y" value="{p["principal_point_offset_y"] + 0.0:.12g}"/>',
            '        <float name="near_clip" value="0.01"/>',
            '        <transform name="to_world">',
            f'            <matrix value="{matrix}"/>',
            "        </transform>",
            '        <film type="hdrfilm">',
            f'            <integer name="width" value="{cam.width}"/>',
            f'            <integer name="height" value="{cam.height}"/>',
            "        </film>",
            "    </sensor>",
        ]
    lines.append("</scene>")
    return "\n".join(lines) + "\n"


def write_rig(path: str | Path, cameras: list[Camera], comment: str = "") -> Path:
    return write_text(path, rig_xml(cameras, comment))


def ring_cameras(
    n: int = 23,
    radius: float = 3.0,
    elevation_deg: float = 0.0,
    look_at_point: tuple[float, float, float] = (0.0, 0.0, 0.0),
    focal: float = 650.0,
    width: int = 512,
    height: int = 512,
    prefix: str = "cam",
    start_deg: float = 0.0,
) -> list[Camera]:
    """``n`` cameras evenly around the +y axis through ``look_at_point``; camera 0 is in front (+z)."""
    target = np.asarray(look_at_point, dtype=np.float64)
    elev = math.radians(elevation_deg)
    cams = []
    for k in range(n):
        a = math.radians(start_deg + 360.0 * k / n)
        offset = radius * np.array([math.sin(a) * math.cos(elev), math.sin(elev), math.cos(a) * math.cos(elev)])
        cams.append(
            look_at(target + offset, target, np.array([0.0, 1.0, 0.0]), focal, width, height, f"{prefix}{k:02d}")
        )
    return cams


def orbit_cameras(n_frames: int = 60, **kwargs) -> list[Camera]:
    """A smooth 360-degree orbit for free-view videos (frame 0 in front)."""
    return ring_cameras(n=n_frames, prefix="orbit", **kwargs)


def place_cameras(cameras: list[Camera], rotation: np.ndarray, translation: np.ndarray) -> list[Camera]:
    """Move body-frame cameras into a world where the body frame is ``x_world = rotation @ x + translation``."""
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    placed = []
    for cam in cameras:
        R = cam.R @ rotation.T
        placed.append(Camera(cam.K.copy(), R, cam.T - R @ translation, cam.width, cam.height, cam.name))
    return placed


def body_rotation(body: BodyModel, bone_transforms: np.ndarray) -> np.ndarray:
    """The posed pelvis's rotation relative to its rest orientation (the body's facing)."""
    pelvis = body.joint_index(body.semantic["pelvis"])
    rest = body.pose(body.zero_pose()).bone_transforms[pelvis, :3, :3]
    return bone_transforms[pelvis, :3, :3] @ rest.T


def place_ring(subject: Subject, n: int, size: int) -> list[Camera]:
    """The shipped ring, centred on the input pose's pelvis, upright for the input camera, facing the body."""
    body = subject.body
    posed = body.pose(*subject.motion.frame(subject.input_index))
    pelvis = body.joint_index(body.semantic["pelvis"])
    rot_body = body_rotation(body, posed.bone_transforms)
    up = -subject.cameras[subject.input_camera].R[1]
    facing = rot_body[:, 2] - (rot_body[:, 2] @ up) * up
    facing /= np.linalg.norm(facing)
    place = np.stack([np.cross(up, facing), up, facing], axis=1)
    cams = read_rig(shipped_rig_path("ring"))
    if n != len(cams):
        cams = ring_cameras(n=n)
    return [c.scaled(size / RING_SIZE) for c in place_cameras(cams, place, posed.bone_transforms[pelvis, :3, 3])]


def shipped_rig_path(name: str) -> Path:
    """Path of a rig shipped in ``scenes/`` (``input``, ``ring`` or ``orbit``)."""
    if name not in SHIPPED_RIGS:
        raise RigError(f"unknown shipped rig {name!r}; choose from {SHIPPED_RIGS}")
    return Path(str(resources.files("elicit_diffrender.scenes").joinpath(f"{name}.xml")))


def default_rigs() -> dict[str, tuple[list[Camera], str]]:
    """The shipped rigs as generated: name -> (cameras, comment)."""
    return {
        "input": (
            ring_cameras(n=1, prefix="input"),
            "ELICIT input camera: 3 m in front of the body, 512x512, f = 650 px (body frame: +y up, facing +z)",
        ),
        "ring": (
            ring_cameras(n=23),
            "ELICIT ring: 23 cameras every 360/23 degrees at 3 m, 512x512, f = 650 px, like ZJU-MoCap's 23",
        ),
        "orbit": (
            orbit_cameras(60, elevation_deg=10.0),
            "ELICIT free-view orbit: 60 frames, 10 degrees elevation, 3 m, 512x512, f = 650 px",
        ),
    }


def main() -> None:
    """Regenerate the shipped rigs in ``scenes/``."""
    out = Path(__file__).resolve().parents[2] / "scenes"
    for name, (cams, comment) in default_rigs().items():
        print(write_rig(out / f"{name}.xml", cams, comment))


if __name__ == "__main__":
    main()
