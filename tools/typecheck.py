"""Type-check the `bagit` package with mypy (`make test` runs this before pytest).

The import name `bagit` maps onto the repository's top-level folders (pyproject's
tool.setuptools.package-dir: bagit -> app/, bagit.common -> common/, ...), which the editable
install resolves with an import hook that mypy does not run. So this lays that mapping out as a
tree of symbolic links under build/typecheck/ (read from pyproject.toml, so it never drifts), runs
mypy on it with the configuration of pyproject's [tool.mypy], and reports every error under its
real path in the repository.

    python tools/typecheck.py [extra mypy flags]
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TREE = ROOT / "build" / "typecheck"


def link_tree() -> dict[str, Path]:
    """build/typecheck/bagit/... as links to the folders of package-dir; {path prefix mypy reports: real folder}."""
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    package_dir: dict[str, str] = cfg["tool"]["setuptools"]["package-dir"]
    top = next(name for name in package_dir if "." not in name)
    if (TREE / top).exists():  # laid anew each time (mypy's cache beside it is kept)
        shutil.rmtree(TREE / top)
    (TREE / top).mkdir(parents=True)
    for entry in (ROOT / package_dir[top]).iterdir():  # the top package's own modules and sub-packages
        if entry.name != "__pycache__":
            os.symlink(entry, TREE / top / entry.name)
    prefixes = {f"{top}/": ROOT / package_dir[top]}
    for name, folder in package_dir.items():
        if name == top:
            continue
        link = TREE.joinpath(*name.split("."))
        os.symlink(ROOT / folder, link)
        prefixes[f"{link.relative_to(TREE)}/"] = ROOT / folder
    return prefixes


def main() -> int:
    prefixes = link_tree()
    cmd = [sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml"), "--cache-dir", str(TREE / ".mypy_cache"),
           *sys.argv[1:], "bagit"]
    out = subprocess.run(cmd, cwd=TREE, capture_output=True, text=True)
    text = out.stdout + out.stderr
    lines = []
    for line in text.splitlines(keepends=True):  # each error under its real path: bagit/common/x.py -> common/x.py
        for link, real in sorted(prefixes.items(), key=lambda kv: -len(kv[0])):  # longest first
            if line.startswith(link):
                line = f"{real.relative_to(ROOT)}/{line[len(link):]}"
                break
        lines.append(line)
    text = "".join(lines)
    sys.stdout.write(text)
    return out.returncode


if __name__ == "__main__":
    sys.exit(main())
