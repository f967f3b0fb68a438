"""``python -m semservo.protocol [--write docs/architecture.md]``: the command tables of
every service, generated from their declarations (printed, or written between the
``<!-- commands:begin -->`` and ``<!-- commands:end -->`` markers of a file)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from semservo.protocol import markdown

BEGIN, END = "<!-- commands:begin (python -m semservo.protocol --write docs/architecture.md) -->", \
    "<!-- commands:end -->"


def replace_block(text: str, block: str) -> str:
    """``text`` with the generated block between its markers replaced by ``block``."""
    start, end = text.index(BEGIN) + len(BEGIN), text.index(END)
    return text[:start] + "\n" + block + text[end:]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m semservo.protocol", description=__doc__)
    parser.add_argument("--write", type=Path, help="replace the block between the markers of this file")
    args = parser.parse_args(argv)
    block = markdown()
    if args.write is None:
        sys.stdout.write(block)
        return 0
    args.write.write_text(replace_block(args.write.read_text(), block))
    print(f"wrote the command tables into {args.write}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
