"""``elicit view``: a self-contained web page that shows an avatar's GLB and plays its animation.

The page is one HTML file: three.js, its glTF loader and orbit controls bundled into one script
(``scripts/viewer/viewer.js``, bundled by esbuild in ``scripts/setup.sh`` into ``VIEWER_BUNDLE``), and
the GLB inlined as base64, since browsers refuse module scripts and ``fetch`` on ``file://``. It opens
offline by double-click; ``avatar.glb`` is written beside it for other tools.
"""

from __future__ import annotations

import base64
from pathlib import Path

from ..core.errors import ElicitError
from ..core.io import atomic_write, write_text

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


def write_viewer(glb: str | Path, out: str | Path, bundle: Path = VIEWER_BUNDLE) -> Path:
    """Write ``out/index.html`` (the page, everything inlined) and ``out/avatar.glb``; returns the page."""
    glb, out = Path(glb), Path(out)
    data = glb.read_bytes()
    if data[:4] != b"glTF":
        raise ViewerError(f"{glb}: not a GLB file (no glTF header)")
    if not bundle.is_file():
        raise ViewerError(f"{bundle}: the viewer bundle is missing; run scripts/setup.sh (it builds it with npm)")
    script = bundle.read_text().replace("</script", "<\\/script")
    page = PAGE.format(glb=base64.b64encode(data).decode(), bundle=script)
    if glb.resolve() != (out / "avatar.glb").resolve():
        atomic_write(out / "avatar.glb", lambda tmp: tmp.write_bytes(data))
    return write_text(out / "index.html", page)
