"""Render the real stages that bind materials and lay them out as one contact sheet (issue 51's "real assets").

Every stage under ``../shared/assets`` that binds a ``UsdPreviewSurface`` or MaterialX surface, and, with
``--usdimaging DIR`` (OpenUSD's ``pxr/usdImaging/usdImagingGL/testenv``, fetched; not committed), its
``testUsdImagingGLDomeLight`` sphere grids and ``testUsdImagingGLGeomSubsets`` beside Storm's baseline images.
Each render is the CLI's (``usdml render STAGE OUT.exr --imageWidth W --preview``) in a subprocess: a traceback
or a non-zero exit is reported, and every warning line it printed is kept (``--json`` writes them).

    .venv/bin/python tools/material_sheet.py --out docs/images/materials_sheet.png --usdimaging /tmp/usdgl/.../testenv
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

ROOT = Path(__file__).resolve().parents[1]
ASSETS = ROOT.parent / "shared" / "assets"
MARKERS = ("UsdPreviewSurface", "ND_standard_surface", "ND_open_pbr", ".mtlx")
#: usdImagingGL stage -> Storm's baseline image (its name in the test's baseline folder)
USDIMAGING = {
    "testUsdImagingGLDomeLight/sphereGrid.usda": "testUsdImagingGLDomeLight_grid.png",
    "testUsdImagingGLDomeLight/sphereGrid_specwf.usda": "testUsdImagingGLDomeLight_grid_specwf.png",
    "testUsdImagingGLDomeLight/sphereMetallic.usda": "testUsdImagingGLDomeLight_metallic.png",
    "testUsdImagingGLDomeLight/sphereRough.usda": "testUsdImagingGLDomeLight_rough.png",
    "testUsdImagingGLGeomSubsets/testUsdImagingGLGeomSubsets.usda": "testUsdImagingGLGeomSubsets_Low.png",
}


def material_stages() -> list[Path]:
    """The asset stages that author a surface shader (by text: binary crate files are read through USD)."""
    from pxr import Usd, UsdShade

    found = []
    for path in sorted(ASSETS.rglob("*.usd*")):
        if path.suffix not in (".usda", ".usd", ".usdc", ".usdz"):
            continue
        try:
            stage = Usd.Stage.Open(str(path))
        except Exception:       # a layer that does not open alone: the suite's asset test covers it
            continue
        if stage is not None and any(p.IsA(UsdShade.Material) for p in stage.Traverse()) and \
                any(p.GetTypeName() in ("Mesh", "Sphere", "Cube", "Cylinder", "Cone", "Capsule")
                    for p in stage.Traverse()):
            found.append(path)
    return found


def render(stage: Path, out: Path, width: int) -> dict:
    r = subprocess.run([sys.executable, "-m", "usdml.cli", "render", str(stage), str(out.with_suffix(".exr")),
                        "--imageWidth", str(width), "--preview", "--pixel-samples", "4"],
                       capture_output=True, text=True, cwd=stage.parent)
    warnings = [line for line in r.stderr.splitlines() if line.startswith("usdml: warning")]
    return {"stage": str(stage), "exit": r.returncode, "traceback": "Traceback" in r.stderr, "warnings": warnings,
            "error": "" if r.returncode == 0 else r.stderr.strip().splitlines()[-1:]}


def read_rgb(path: Path, width: int) -> np.ndarray:
    """An image as (H, W, 3) float in [0, 1], scaled to ``width``, composited over mid grey."""
    spec = oiio.ImageBuf(str(path)).spec()
    h = max(1, round(spec.height * width / spec.width))
    buf = oiio.ImageBufAlgo.resize(oiio.ImageBuf(str(path)), roi=oiio.ROI(0, width, 0, h, 0, 1, 0, spec.nchannels))
    px = np.asarray(buf.get_pixels(oiio.FLOAT)).reshape(h, width, -1)
    rgb = px[..., :3] if px.shape[2] >= 3 else np.repeat(px[..., :1], 3, axis=2)
    if px.shape[2] == 4:
        rgb = rgb + (1.0 - px[..., 3:4]) * 0.5
    return np.clip(rgb, 0.0, 1.0)


def label(tile: np.ndarray, text: str) -> np.ndarray:
    """``tile`` with ``text`` in its top-left corner (OpenImageIO's text rendering; unchanged where it has no font)."""
    buf = oiio.ImageBuf(oiio.ImageSpec(tile.shape[1], tile.shape[0], 3, oiio.FLOAT))
    buf.set_pixels(oiio.ROI(0, tile.shape[1], 0, tile.shape[0], 0, 1, 0, 3), np.ascontiguousarray(tile, np.float32))
    if oiio.ImageBufAlgo.render_text(buf, 4, 14, text, 12, "", (1.0, 1.0, 0.2)):
        return np.asarray(buf.get_pixels(oiio.FLOAT)).reshape(tile.shape)
    return tile


def sheet(tiles: list[np.ndarray], columns: int, width: int) -> np.ndarray:
    rows = [tiles[i:i + columns] for i in range(0, len(tiles), columns)]
    height = max(t.shape[0] for t in tiles)
    out = np.full((len(rows) * (height + 4), columns * (width + 4), 3), 1.0)
    for r, row in enumerate(rows):
        for c, t in enumerate(row):
            out[r * (height + 4):r * (height + 4) + t.shape[0], c * (width + 4):c * (width + 4) + t.shape[1]] = t
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "images" / "materials_sheet.png"))
    ap.add_argument("--usdimaging", help="OpenUSD's pxr/usdImaging/usdImagingGL/testenv folder (fetched)")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--json", help="write each render's exit, traceback flag and warnings here")
    args = ap.parse_args(argv)
    jobs = [(s, None) for s in material_stages()]
    if args.usdimaging:
        base = Path(args.usdimaging)
        for stage, baseline in USDIMAGING.items():
            if (base / stage).exists():
                jobs.append((base / stage, base / Path(stage).parent / "baseline" / baseline))
    tiles, report = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (stage, baseline) in enumerate(jobs):
            out = Path(tmp) / f"r{i}.png"
            if baseline is not None and tiles and len(tiles) % 2:   # pairs start on an even column
                tiles.append(np.ones_like(tiles[-1]))
            result = render(stage, out, args.width)
            report.append(result)
            name = str(stage.relative_to(stage.parents[2]))
            print(f"{name}: exit {result['exit']}, {len(result['warnings'])} warning(s)"
                  + (", TRACEBACK" if result["traceback"] else ""), flush=True)
            tiles.append(label(read_rgb(out, args.width) if out.exists() else np.zeros((args.width // 2, args.width, 3)),
                               Path(name).name))
            if baseline is not None:        # usdImagingGL's: Storm's image beside ours
                tiles.append(label(read_rgb(baseline, args.width) if baseline.exists()
                                   else np.ones_like(tiles[-1]), "Storm baseline"))
    image = sheet(tiles, 4, args.width)
    out = oiio.ImageOutput.create(args.out)
    out.open(args.out, oiio.ImageSpec(image.shape[1], image.shape[0], 3, oiio.UINT8))
    out.write_image((image * 255 + 0.5).astype(np.uint8))
    out.close()
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 1 if any(r["traceback"] or r["exit"] for r in report) else 0


if __name__ == "__main__":
    sys.exit(main())
