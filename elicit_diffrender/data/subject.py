"""The subject folder format ``elicit-subject/1``: read, validate and write.

    subject.json   {"format": "elicit-subject/1", "body": {...}, "input": {"camera": "cam00", "frame": 0},
                    optional "inputs": [{"camera": ..., "frame": ...}, ...]}
    cameras.json   {"cam00": {"K": 3x3, "R": 3x3, "T": [x, y, z], "width": W, "height": H}, ...}
    motion.npz     pose (F, J, 3), global_orient (F, 3), transl (F, 3), optional frame_ids (F,)
    images/<cam>/<frame:06d>.png   RGB
    masks/<cam>/<frame:06d>.png    1-, 8- or 16-bit, above half of full scale is the person

``frame`` is a motion frame id (``frame_ids``, default 0..F-1). Fitting needs only the input view, or
the input views: ``inputs`` lists every photo of a multi-photo subject (each its own camera and frame),
its first entry equal to ``input``, which stays the view that novel views are measured from. Any other
image is ground truth for evaluation. Every problem is reported as a ``SubjectError``
naming the file and the field.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..body import BodyModel
from ..core.cameras import Camera
from ..core.checks import numeric, read_image, read_mask, safe_name
from ..core.errors import ElicitError
from ..core.io import read_json, write_image, write_json
from .motions import Motion, MotionError, load_motion_npz

FORMAT = "elicit-subject/1"
JOINT_COUNTS = {"anny": 104, "smpl": 24, "smplx": 22}


class SubjectError(ElicitError):
    """A subject folder that does not follow ``elicit-subject/1``."""


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise SubjectError(f"{path}: file not found")
    data = read_json(path, SubjectError)
    if not isinstance(data, dict):
        raise SubjectError(f"{path}: the top level must be an object")
    return data


def parse_cameras(data: dict, path: Path) -> dict[str, Camera]:
    if not data:
        raise SubjectError(f"{path}: no cameras")
    cams = {}
    for name, c in data.items():
        where = f"{path} camera {name!r}"
        safe_name(name, where, SubjectError)  # it names the folders images/<camera>/ and masks/<camera>/
        if not isinstance(c, dict):
            raise SubjectError(f"{where}: must be an object")
        for key in ("K", "R", "T", "width", "height"):
            if key not in c:
                raise SubjectError(f"{where}: missing field '{key}'")
        K = numeric(c["K"], f"{where} field 'K'", (3, 3), SubjectError)
        R = numeric(c["R"], f"{where} field 'R'", (3, 3), SubjectError)
        T = numeric(c["T"], f"{where} field 'T'", (3,), SubjectError)
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
            raise SubjectError(f"{where} field 'R': not a rotation matrix")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise SubjectError(f"{where} field 'K': focal lengths must be positive")
        for key in ("width", "height"):
            if not isinstance(c[key], int) or c[key] <= 0:
                raise SubjectError(f"{where} field '{key}': must be a positive integer, got {c[key]!r}")
        cams[name] = Camera(K, R, T, c["width"], c["height"], name)
    return cams


@dataclass
class Subject:
    root: Path
    body_spec: dict
    cameras: dict[str, Camera]
    motion: Motion
    input_camera: str
    input_frame: int
    meta: dict = field(default_factory=dict)
    inputs: list[tuple[str, int]] = field(default_factory=list)  # every input view, the first is the input
    _body: BodyModel | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not self.inputs:
            self.inputs = [(self.input_camera, self.input_frame)]

    @property
    def body(self) -> BodyModel:
        if self._body is None:
            from ..body import load_body

            self._body = load_body(self.body_spec)
        return self._body

    @property
    def input_index(self) -> int:
        """Index of the input frame in the motion."""
        return self.frame_index(self.input_frame)

    def frame_index(self, frame: int) -> int:
        """Index of a frame id in the motion."""
        return int(np.nonzero(self.motion.frame_ids == frame)[0][0])

    def image_path(self, camera: str, frame: int) -> Path:
        return self.root / "images" / camera / f"{frame:06d}.png"

    def mask_path(self, camera: str, frame: int) -> Path:
        return self.root / "masks" / camera / f"{frame:06d}.png"

    def has_view(self, camera: str, frame: int) -> bool:
        return self.image_path(camera, frame).is_file() and self.mask_path(camera, frame).is_file()

    def image(self, camera: str, frame: int) -> np.ndarray:
        """(H, W, 3) float RGB in [0, 1]."""
        cam = self.cameras[camera]
        return read_image(self.image_path(camera, frame), "image", (cam.height, cam.width), error=SubjectError)[0]

    def mask(self, camera: str, frame: int) -> np.ndarray:
        """(H, W) bool person mask."""
        cam = self.cameras[camera]
        return read_mask(self.mask_path(camera, frame), "mask", (cam.height, cam.width), error=SubjectError)

    def views(self) -> list[tuple[str, int]]:
        """Every (camera, frame) with both an image and a mask."""
        out = []
        for cam in self.cameras:
            for f in self.motion.frame_ids.tolist():
                if self.has_view(cam, f):
                    out.append((cam, f))
        return out


def load_subject(path: str | Path) -> Subject:
    """Read and validate a subject folder."""
    root = Path(path)
    if not root.is_dir():
        raise SubjectError(f"{root}: subject folder not found")
    meta = _read_json(root / "subject.json")
    where = root / "subject.json"
    if meta.get("format") != FORMAT:
        raise SubjectError(f"{where}: field 'format' must be {FORMAT!r}, got {meta.get('format')!r}")
    body = meta.get("body")
    if not isinstance(body, dict) or body.get("model") not in JOINT_COUNTS:
        raise SubjectError(f"{where}: field 'body' must be an object with 'model' one of {sorted(JOINT_COUNTS)}")
    if body["model"] == "anny" and not isinstance(body.get("phenotype", {}), dict):
        raise SubjectError(f"{where}: field 'body.phenotype' must be an object")
    if body["model"] != "anny" and "betas" in body:
        numeric(body["betas"], f"{where} field 'body.betas'", (-1,), SubjectError)
    inp = meta.get("input")
    if not isinstance(inp, dict) or not isinstance(inp.get("camera"), str) or "frame" not in inp:
        raise SubjectError(f'{where}: field \'input\' must be {{"camera": "<name>", "frame": <frame id>}}')
    cameras = parse_cameras(_read_json(root / "cameras.json"), root / "cameras.json")
    if inp["camera"] not in cameras:
        raise SubjectError(
            f"{where}: field 'input.camera' names unknown camera {inp['camera']!r}; "
            f"cameras.json has {sorted(cameras)[:8]}"
        )
    try:
        motion = load_motion_npz(root / "motion.npz", JOINT_COUNTS[body["model"]])
    except MotionError as exc:
        raise SubjectError(str(exc)) from None
    if not isinstance(inp["frame"], int) or inp["frame"] not in motion.frame_ids.tolist():
        raise SubjectError(f"{where}: field 'input.frame' = {inp['frame']!r} is not a frame id of motion.npz")
    inputs = parse_inputs(meta.get("inputs", [inp]), cameras, motion, where)
    if inputs[0] != (inp["camera"], inp["frame"]):
        raise SubjectError(f"{where}: field 'inputs' must start with the view that 'input' names")
    subject = Subject(root, body, cameras, motion, inp["camera"], inp["frame"], meta, inputs)
    for cam, frame in inputs:
        subject.image(cam, frame)  # every input view must exist and match its camera
        if not subject.mask(cam, frame).any():
            raise SubjectError(f"{subject.mask_path(cam, frame)}: the input mask is empty")
    return subject


def parse_inputs(entries, cameras: dict[str, Camera], motion: Motion, where: Path) -> list[tuple[str, int]]:
    """``inputs``: a non-empty list of distinct {"camera": name, "frame": frame id} of known cameras and frames."""
    if not isinstance(entries, list) or not entries:
        raise SubjectError(f'{where}: field \'inputs\' must be a non-empty list of {{"camera": ..., "frame": ...}}')
    out = []
    for k, entry in enumerate(entries):
        cam = entry.get("camera") if isinstance(entry, dict) else None
        frame = entry.get("frame") if isinstance(entry, dict) else None
        if cam not in cameras or not isinstance(frame, int) or frame not in motion.frame_ids.tolist():
            raise SubjectError(
                f"{where}: field 'inputs[{k}]' = {entry!r} must name a camera of cameras.json and a frame id of "
                "motion.npz"
            )
        out.append((cam, frame))
    if len(set(out)) != len(out):
        raise SubjectError(f"{where}: field 'inputs' lists a view twice")
    return out


def write_subject(
    root: str | Path,
    body_spec: dict,
    cameras: dict[str, Camera],
    motion: Motion,
    input_camera: str,
    input_frame: int,
    views: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]],
    extra: dict | None = None,
    inputs: list[tuple[str, int]] | None = None,
) -> Path:
    """Write a subject folder; ``views`` maps (camera, frame) to (RGB float [0,1], mask bool); ``inputs``, every
    input view of a multi-photo subject (the first is ``(input_camera, input_frame)``)."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    motion.save(root / "motion.npz")
    write_json(root / "cameras.json", {name: cam.to_dict() for name, cam in cameras.items()})
    for (cam, frame), (rgb, mask) in views.items():
        write_image(root / "images" / cam / f"{frame:06d}.png", rgb)
        write_image(root / "masks" / cam / f"{frame:06d}.png", (np.asarray(mask) > 0.5).astype(np.uint8) * 255)
    meta = {"format": FORMAT, "body": body_spec, "input": {"camera": input_camera, "frame": int(input_frame)}}
    if inputs is not None and len(inputs) > 1:
        meta["inputs"] = [{"camera": cam, "frame": int(frame)} for cam, frame in inputs]
    meta.update(extra or {})
    write_json(root / "subject.json", meta)  # last: a folder with subject.json is complete
    return root
