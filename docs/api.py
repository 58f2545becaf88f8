"""Build the API reference from the docstrings: ``python docs/api.py`` writes docs/api/index.html
(and a page per module) with pdoc; ``python docs/api.py --out DIR`` writes elsewhere."""
from __future__ import annotations

import argparse
import os
from pathlib import Path


def modules() -> list[str]:
    """statfit and every module in it (the package's ``__all__`` would hide the submodules)."""
    import pkgutil

    import statfit

    return ["statfit", *sorted(m.name for m in pkgutil.walk_packages(statfit.__path__, "statfit."))]


def specs(names: list[str]) -> list[str]:
    """``names`` less those pdoc already adds when it walks an earlier one (a package without
    ``__all__`` brings its submodules): the same pages, without pdoc's warning for each module
    named twice."""
    from pdoc.extract import walk_specs

    covered: set[str] = set()
    kept = []
    for name in names:
        if name not in covered:
            kept.append(name)
            covered.update(walk_specs([name]))
    return kept


def build(out: Path) -> None:
    os.environ.setdefault("PDOC_ALLOW_EXEC", "1")  # our modules run no subprocess at import; platform's uname may
    import pdoc

    pdoc.pdoc(*specs(modules()), output_directory=out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "api")
    args = parser.parse_args()
    build(args.out)
    print(f"wrote {args.out / 'index.html'}")


if __name__ == "__main__":
    main()
