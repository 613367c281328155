"""mypy over the installed package names: `python -m tools.typecheck [mypy options]`.

mypy names a module after its folders, so `api/access.py` would be `api.access`, while
the program imports it as `mapservice.api.access`. Here every file is handed to mypy with
its installed name (installed_layout), so module names, imports between the components and
pyproject's per-module settings all use the names the program uses. The options are
pyproject's [tool.mypy]; extra command-line options are passed on.
"""

from __future__ import annotations

import sys
import time

from mypy.fscache import FileSystemCache
from mypy.main import process_options, run_build
from mypy.modulefinder import BuildSource
from mypy.util import FancyFormatter, count_stats

from tools.installed_layout import ROOT, modules


def sources() -> list[BuildSource]:
    """Every module of the product, and this tooling, under the name it is imported by."""
    named = {**modules(), **{f"tools.{p.stem}": p for p in (ROOT / "tools").glob("*.py")}}
    named["tools"] = named.pop("tools.__init__")
    return [
        BuildSource(str(path.relative_to(ROOT)), module, base_dir=str(ROOT))
        for module, path in sorted(named.items())
    ]


def main(argv: list[str]) -> int:
    started = time.time()
    fscache = FileSystemCache()
    # A target is required to parse the options; the sources are then replaced by ours.
    _, options = process_options(
        ["--config-file", str(ROOT / "pyproject.toml"), *argv, "-c", ""], fscache=fscache
    )
    checked = sources()
    _, messages, blockers = run_build(checked, options, fscache, started, sys.stdout, sys.stderr)
    formatter = FancyFormatter(sys.stdout, sys.stderr, options.hide_error_codes)
    errors, _notes, files = count_stats(messages)
    if errors:
        print(formatter.format_error(errors, files, len(checked), blockers=blockers), flush=True)
        return 2 if blockers else 1
    print(formatter.format_success(len(checked)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
