"""Copy figures of runs into docs/img/ as small PNGs for docs/figures.md.

    python scripts/gallery_images.py <dest dir> <prefix> <png> [<png> ...]

Each figure is reduced to a 256-colour palette (and scaled down, if needed) until it is below
--max-kb (default 150) kilobytes; it is written as <dest dir>/<prefix>_<name>.png.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

from PIL import Image


def small_png(src: Path, max_kb: int) -> bytes:
    img = Image.open(src).convert("RGB")
    scale = 1.0
    while True:
        im = img if scale == 1.0 else img.resize((int(img.width * scale), int(img.height * scale)), Image.LANCZOS)
        buf = io.BytesIO()
        im.quantize(colors=256, method=Image.Quantize.FASTOCTREE).save(buf, format="PNG", optimize=True)
        if buf.tell() <= max_kb * 1024 or scale < 0.3:
            return buf.getvalue()
        scale *= 0.85


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dest", type=Path)
    ap.add_argument("prefix")
    ap.add_argument("pngs", type=Path, nargs="+")
    ap.add_argument("--max-kb", type=int, default=150)
    args = ap.parse_args()
    args.dest.mkdir(parents=True, exist_ok=True)
    for src in args.pngs:
        out = args.dest / f"{args.prefix}_{src.stem}.png"
        data = small_png(src, args.max_kb)
        out.write_bytes(data)
        print(f"{out}: {len(data) / 1024:.0f} KB (from {src.stat().st_size / 1024:.0f} KB)")


if __name__ == "__main__":
    main()
