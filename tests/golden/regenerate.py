"""Recompute the golden solve outputs, print what changed, rewrite the files.

    python tests/golden/regenerate.py [--check] [--force] [CASE ...]

Per case: the largest rotation change (rad) and position change (mm) against the
stored golden, every frame and bone beyond tolerance, flag changes. Without
``--check`` a case's file is rewritten when any stored (rounded) value differs, or with
``--force``; ``--check`` only reports and exits 1 when a case is beyond tolerance.
Exit 2 when the shared datasets folder is missing (real takes cannot be computed).
See tests/golden/README.md.
"""

from __future__ import annotations

import argparse
import json
import sys

import golden_cases as g


def _same(doc: dict | None, new: dict) -> bool:
    """Every stored value equal (the producing software aside)."""
    if doc is None:
        return False
    a, b = ({**d, "produced_by": None} for d in (doc, new))
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def _report(
    case: g.Case, doc: dict | None, new: dict, computed: g.Computed, same: bool
) -> bool:
    """Print what changed; True when beyond tolerance."""
    if doc is None:
        print(f"{case.name}: new golden ({len(new['frames'])} frames)")
        return True
    cmp = g.compare(case, doc, computed)
    angle = ", ".join(f"{k} {v:.3g} rad" for k, v in cmp.max_angle_rad.items())
    mm = ", ".join(f"{k} {v:.3g} mm" for k, v in cmp.max_mm.items())
    status = "identical" if same else ("within tolerance" if cmp.ok else "CHANGED")
    print(f"{case.name} [{case.take or 'synthetic'}]: {status}")
    if cmp.max_angle_rad:
        print(f"  max change: {angle}; {mm}; flag changes {cmp.flag_changes}")
    if not cmp.ok:
        print("  " + g.failure_message(case, cmp, limit=25).replace("\n", "\n  "))
    return not cmp.ok


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cases", nargs="*", metavar="CASE", help="default: all")
    parser.add_argument("--check", action="store_true", help="report only")
    parser.add_argument("--force", action="store_true", help="rewrite every file")
    args = parser.parse_args(argv)
    unknown = [n for n in args.cases if n not in g.CASE_BY_NAME]
    if unknown:
        parser.error(f"unknown case(s) {unknown}; known: {', '.join(g.CASE_BY_NAME)}")
    cases = [g.CASE_BY_NAME[n] for n in args.cases] or list(g.CASES)
    if any(c.needs_datasets for c in cases) and not g.DATASETS.is_dir():
        print(f"shared datasets folder not found at {g.DATASETS}", file=sys.stderr)
        return 2
    beyond = 0
    for case in cases:
        path = g.golden_path(case)
        doc = g.load_golden(case) if path.exists() else None
        computed = g.compute(case)
        new = g.to_golden(case, computed)
        same = _same(doc, new)
        beyond += _report(case, doc, new, computed, same)
        if args.check or (same and not args.force):
            continue
        path.write_text(g.dumps(new))
        print(f"  wrote {path.relative_to(g.REPO_ROOT)} ({path.stat().st_size} bytes)")
    if args.check and beyond:
        print(f"{beyond} case(s) beyond tolerance")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
