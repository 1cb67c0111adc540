#!/usr/bin/env python3
"""Fails when README.md states a ratio or a speed that BENCHMARKS.md does not contain.

A ratio is a number or a range followed by `x` ("1.5x", "0.86–0.97x", "9–10x"); a speed is a
number or a range followed by a rate unit ("11.5 M samples/s", "75–165 fps", "50 GFLOP/s").
Each must appear in BENCHMARKS.md as written, up to the dash (en dash or hyphen) and spaces,
and not as the tail of a longer number, outside what BENCHMARKS.md marks superseded: a section
whose first paragraph starts with "**Superseded" (up to the next heading of its level or
above), and any paragraph that starts with "Superseded" or "**Superseded". So a figure that a
later run replaced cannot be quoted. Grid sizes ("512x512", "5x5x5") are not ratios.
Usage: deploy/check_claims.py [README.md [BENCHMARKS.md]]; run by .ci/run.
"""
import re
import sys

NUM = r"\d+(?:\.\d+)?"
RANGE = rf"{NUM}(?:\s*[–—-]\s*{NUM})?"
RATIO = re.compile(rf"(?<![\w.]){RANGE}\s?x(?![\w])")
RATE = r"(?:[kKMG]\s?)?(?:samples|voxels|bricks|frames|rays|images|requests|steps)/s|fps|[GT]FLOP/s|[KMG]i?B/s"
SPEED = re.compile(rf"(?<![\w.]){RANGE}\s*(?:{RATE})(?![\w])")
# Figures of speech and layouts, not measurements: (text around the match, why).
NOT_CLAIMS = [("a 2x pyramid", "the store's pyramid halves each level")]


def norm(s):
    """One spelling: dashes as '-', no spaces, no emphasis."""
    return re.sub(r"\s+", "", re.sub("[–—]", "-", s)).replace("*", "")


def current(text):
    """BENCHMARKS.md without its superseded sections and paragraphs."""
    paras = re.split(r"\n\s*\n", text)
    superseded = re.compile(r"^\s*(\*\*)?Superseded")
    out, skip = [], None  # skip: the level of the superseded section being dropped
    for i, p in enumerate(paras):
        h = re.match(r"^(#+)\s", p)
        if h:
            level = len(h.group(1))
            if skip is not None and level <= skip:
                skip = None
            nxt = paras[i + 1] if i + 1 < len(paras) else ""
            if skip is None and nxt.lstrip().startswith("**Superseded"):
                skip = level
        if skip is None and not superseded.match(p):
            out.append(p)
    return "\n\n".join(out)


def claims(text):
    for kind, rx in (("ratio", RATIO), ("speed", SPEED)):
        for m in rx.finditer(text):
            around = text[max(0, m.start() - 20) : m.end() + 20].replace("\n", " ")
            if any(n in around for n, _ in NOT_CLAIMS):
                continue
            yield kind, text.count("\n", 0, m.start()) + 1, m.group(0), around


def main():
    readme = sys.argv[1] if len(sys.argv) > 1 else "README.md"
    bench = sys.argv[2] if len(sys.argv) > 2 else "BENCHMARKS.md"
    text, figures = open(readme, encoding="utf-8").read(), norm(current(open(bench, encoding="utf-8").read()))
    seen, missing = 0, []
    for kind, line, claim, around in claims(text):
        seen += 1
        if not re.search(r"(?<![\d.])" + re.escape(norm(claim)), figures):
            missing.append(f"{readme}:{line}: {kind} '{claim}' is not in {bench} (…{around}…)")
    for m in missing:
        print(m)
    print(f"check_claims: {seen} ratios and speeds in {readme}, {len(missing)} not in {bench}")
    return 1 if missing or seen == 0 else 0


if __name__ == "__main__":
    sys.exit(main())
