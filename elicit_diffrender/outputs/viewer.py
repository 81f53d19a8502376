"""``elicit view``: a self-contained web page that shows an avatar's GLB and plays its animation.

The page is one HTML file: three.js, its glTF loader and orbit controls bundled into one script
(``scripts/viewer/viewer.js``, bundled by esbuild in ``scripts/setup.sh`` into ``VIEWER_BUNDLE``), and
the GLB inlined as base64, since browsers refuse module scripts and ``fetch`` on ``file://``. It opens
offline by double-click; ``avatar.glb`` is written beside it for other tools.
"""

from __future__ import annotations

import base64
import struct
from pathlib import Path

from ..core.errors import ElicitError
from ..core.io import atomic_write, parse_json, write_text

ROOT = Path(__file__).resolve().parents[2]
VIEWER_BUNDLE = ROOT / ".tools" / "viewer" / "viewer.js"


class ViewerError(ElicitError):
    """The page cannot be written (no bundle, not a GLB)."""


PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>avatar</title>
<style>html, body {{ margin: 0; height: 100%; overflow: hidden; background: #202020; }}</style>
</head>
<body>
<script id="avatar" type="application/octet-stream">{glb}</script>
<script>{bundle}</script>
</body>
</html>
"""


def glb_problem(data: bytes) -> str:
    """Why ``data`` is not a glTF 2.0 binary ("" if it is one): the 12-byte header (``glTF``, version 2, the
    file's length) and a first chunk of JSON that fits in the file and holds a glTF ``asset``."""
    if len(data) < 20 or data[:4] != b"glTF":
        return "no glTF header"
    version, length = struct.unpack_from("<II", data, 4)
    chunk_length, chunk_type = struct.unpack_from("<I4s", data, 12)
    if version != 2:
        return f"glTF version {version}, expected 2"
    if length != len(data):
        return f"its header says {length} bytes, the file has {len(data)}"
    if chunk_type != b"JSON" or 20 + chunk_length > len(data):
        return "no JSON chunk within the file"
    try:
        doc = parse_json(data[20 : 20 + chunk_length], "the JSON chunk")
    except ElicitError as exc:
        return str(exc)
    return "" if isinstance(doc, dict) and isinstance(doc.get("asset"), dict) else "the JSON chunk has no asset"


def write_viewer(glb: str | Path, out: str | Path, bundle: Path = VIEWER_BUNDLE) -> Path:
    """Write ``out/index.html`` (the page, everything inlined) and ``out/avatar.glb``; returns the page."""
    glb, out = Path(glb), Path(out)
    data = glb.read_bytes()
    problem = glb_problem(data)
    if problem:
        raise ViewerError(f"{glb}: not a GLB file ({problem})")
    if not bundle.is_file():
        raise ViewerError(f"{bundle}: the viewer bundle is missing; run scripts/setup.sh (it builds it with npm)")
    script = bundle.read_text().replace("</script", "<\\/script")
    page = PAGE.format(glb=base64.b64encode(data).decode(), bundle=script)
    if glb.resolve() != (out / "avatar.glb").resolve():
        atomic_write(out / "avatar.glb", lambda tmp: tmp.write_bytes(data))
    return write_text(out / "index.html", page)
