"""The imports of Python source files, read statically (ast): every import statement, in functions too."""
from __future__ import annotations

import ast
from collections.abc import Iterator
from dataclasses import dataclass
import importlib.util
from pathlib import Path
import sys

ROOT = Path(__file__).resolve().parents[1]
# Standard since Python 3.14; the package falls back to a backport on older ones.
NEWER_STANDARD_MODULES = frozenset({'compression'})


@dataclass(frozen=True)
class SourceImport:
    """One name an import statement imports: ``a.b`` for ``import a.b``, ``a.b`` for ``from a import b``."""

    path: Path
    line: int
    name: str

    @property
    def top(self) -> str:
        return self.name.partition('.')[0]

    def __str__(self) -> str:
        return f'{self.path.relative_to(ROOT)}:{self.line} imports {self.name}'


def module_name(path: Path) -> str:
    """Return the dotted name of the module at ``path`` (under ROOT)."""
    return '.'.join(path.relative_to(ROOT).with_suffix('').parts).removesuffix('.__init__')


def imports_in(path: Path) -> Iterator[SourceImport]:
    """Yield every name that the file at ``path`` imports, relative imports made absolute."""
    package = module_name(path) if path.name == '__init__.py' else module_name(path).rpartition('.')[0]
    for node in ast_nodes(path):
        if isinstance(node, ast.Import):
            yield from (SourceImport(path, node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = importlib.util.resolve_name('.' * node.level + (node.module or ''), package) if node.level \
                else node.module
            yield from (SourceImport(path, node.lineno, base if alias.name == '*' else f'{base}.{alias.name}')
                        for alias in node.names)


def ast_nodes(path: Path) -> Iterator[ast.AST]:
    """Yield every node of the file at ``path``."""
    return ast.walk(ast.parse(path.read_text(), str(path)))


def python_files(*directories: str) -> list[Path]:
    """Return the Python files under ``directories`` (relative to ROOT), sorted."""
    return sorted(path for directory in directories for path in (ROOT / directory).rglob('*.py'))


def third_party(found: SourceImport, local: frozenset[str] = frozenset()) -> bool:
    """Return whether ``found`` names neither the standard library, vlp_ros nor one of the ``local`` modules."""
    return found.top not in sys.stdlib_module_names | NEWER_STANDARD_MODULES | {'vlp_ros'} | local
