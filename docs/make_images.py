"""Refresh the quick-looks shown by the guides from the runs they describe.

    tiledsm run recipes/demo.yaml --out runs/demo
    tiledsm run recipes/deformation.yaml --out runs/deformation
    python docs/make_images.py runs/demo runs/deformation

Each PNG is reduced (640 px wide, 1000 for the displacement figure) and quantised to 128 colours,
which keeps it under 300 kB.
"""

from __future__ import annotations

import sys
from pathlib import Path

from PIL import Image

HERE = Path(__file__).resolve().parent / "images"


def reduce(src: Path, dst: Path, width: int) -> None:
    im = Image.open(src)
    if im.size[0] > width:
        im = im.resize((width, round(im.size[1] * width / im.size[0])), Image.LANCZOS)
    im.convert("RGB").quantize(colors=128, method=Image.MEDIANCUT, dither=Image.FLOYDSTEINBERG).save(dst, optimize=True)


def main(demo: str, deformation: str) -> None:
    demo_dir, deformation_dir = Path(demo), Path(deformation)
    for name, src, width in [
        ("demo_dsm.png", demo_dir / "dsm.png", 640),
        ("demo_dsm_error.png", demo_dir / "dsm_error.png", 640),
        ("deformation_dh.png", deformation_dir / "compare" / "dh.png", 640),
        ("deformation_dh_hist.png", deformation_dir / "compare" / "dh_hist.png", 640),
        ("displacement.png", deformation_dir / "displacement" / "displacement.png", 1000),
        ("displacement_profiles.png", deformation_dir / "displacement" / "profiles.png", 700),
    ]:
        reduce(src, HERE / name, width)
        print(HERE / name, (HERE / name).stat().st_size, "bytes")


if __name__ == "__main__":
    main(*sys.argv[1:3])
