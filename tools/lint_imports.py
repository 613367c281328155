"""import-linter over the installed package names: `python -m tools.lint_imports
[--source-root DIR] [lint-imports options]`.

import-linter (grimp) finds a package's modules by walking the folder Python would import
it from, and refuses a subpackage as a root. The components are installed as
`mapservice.*` subpackages from folders beside `mapservice/`, so here each mapped package is
a root of its own, found in its folder (installed_layout): the contracts see the whole
service, under the names the program imports. `--source-root` reads the folders from
another tree laid out like the checkout (the contract tests add breaking modules to one).
"""

from __future__ import annotations

import sys
from pathlib import Path

from grimp.adaptors.packagefinder import ImportLibPackageFinder
from grimp.application.config import settings
from grimp.application.ports.filesystem import AbstractFileSystem
from importlinter.cli import lint_imports_command

from tools.installed_layout import ROOT, package_dirs


class MappedPackageFinder(ImportLibPackageFinder):
    """A mapped package is found in its folder; any other package as Python finds it."""

    def __init__(self, source_root: Path) -> None:
        self.folders = package_dirs(source_root)

    def determine_package_directories(
        self, package_name: str, file_system: AbstractFileSystem
    ) -> set[str]:
        if package_name in self.folders:
            return {str(self.folders[package_name])}
        return super().determine_package_directories(package_name, file_system)


def main(argv: list[str]) -> None:
    source_root = ROOT
    if argv[:1] == ["--source-root"]:
        source_root, argv = Path(argv[1]).resolve(), argv[2:]
    settings.configure(PACKAGE_FINDER=MappedPackageFinder(source_root))
    lint_imports_command.main(["--config", str(ROOT / "pyproject.toml"), *argv])


if __name__ == "__main__":
    main(sys.argv[1:])
