"""Where trained models are cached, what the cache holds, and its integrity helpers.

The cache directory is ``--cache DIR``, else ``$KKL_BENCH_CACHE``, else
``.kkl_bench_cache`` in the working directory. Estimators store content-keyed
files under ``<cache>/<kind>/`` (see :mod:`kkl_bench.kkl.cache`), each with a
``.sha256`` sidecar that is checked before loading; ``unrolled_kernels/`` and
``bound_kernels/`` hold the filters' generated kernels (:func:`import_generated`,
:mod:`kkl_bench.support.kernel_cache`).
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib
import importlib.util
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType


def default_cache_dir() -> Path:
    """``$KKL_BENCH_CACHE`` if set, else ``.kkl_bench_cache`` in the working directory."""
    return Path(os.environ.get("KKL_BENCH_CACHE", ".kkl_bench_cache"))


@functools.cache
def code_digest() -> str:
    """A digest of every Python file of kkl_bench's packages (the core, its systems and
    estimators): what the artifacts made from its code depend on (the bound kernels of
    :mod:`kkl_bench.support.kernel_cache`)."""
    digest = hashlib.sha256()
    roots = {Path(path) for name in ("", ".systems", ".estimators") for path in _paths(name)}
    for root in sorted(roots):
        for path in sorted(root.rglob("*.py")):
            digest.update(path.relative_to(root).as_posix().encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def _paths(subpackage: str) -> list[str]:
    return list(importlib.import_module(f"kkl_bench{subpackage}").__path__)


@functools.cache
def imported_code_digest(module: str) -> str:
    """A digest of the source of ``module`` and of every module of its top-level package
    that it imports, directly or through those (:func:`imported_modules`): the code of that
    package which calling ``module``'s functions can run, short of objects passed to them
    and modules loaded by name (an estimator found in the registry)."""
    digest = hashlib.sha256()
    for name, source in sorted(_imported_sources(module).items()):
        digest.update(name.encode())
        digest.update(source)
    return digest.hexdigest()[:16]


def imported_modules(module: str) -> list[str]:
    """``module`` and the modules of its top-level package that it imports, directly or
    through those, sorted: read from their absolute import statements, those inside
    functions included, without importing them."""
    return sorted(_imported_sources(module))


def _imported_sources(module: str) -> dict[str, bytes]:
    """Each module of :func:`imported_modules` -> its source (empty for a module without a
    source file: a namespace package, a name that is not found)."""
    package = module.partition(".")[0]
    sources: dict[str, bytes] = {}
    pending = [module]
    while pending:
        name = pending.pop()
        if name not in sources:
            spec = importlib.util.find_spec(name)
            found = spec is not None and spec.has_location and spec.origin
            sources[name] = Path(spec.origin).read_bytes() if found else b""
            pending += _imports(sources[name], package)
    return sources


def _imports(source: bytes, package: str) -> list[str]:
    """The modules of ``package`` that ``source``'s absolute import statements name: for
    ``from A import B``, ``A.B`` where that is a module, else ``A``."""
    names = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names if a.name.partition(".")[0] == package]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module.partition(".")[0] != package:
                continue
            spec = importlib.util.find_spec(node.module)
            is_package = spec is not None and spec.submodule_search_locations is not None
            for alias in node.names:
                submodule = f"{node.module}.{alias.name}"
                found = is_package and importlib.util.find_spec(submodule)
                names.append(submodule if found else node.module)
    return names


def checksum_path(path: Path) -> Path:
    """The SHA-256 sidecar of ``path``."""
    return path.with_name(path.name + ".sha256")


def sha256_of(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_atomically(path: Path, text: str) -> None:
    """Write ``text`` to a temporary file beside ``path``, then rename it into place."""
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(handle, "w") as file:
        file.write(text)
    os.replace(temporary, path)


@dataclass(frozen=True)
class CacheKind:
    """Entries of one kind (e.g. ``kkl-phase1``): count, bytes, and damaged entries."""

    kind: str
    entries: int
    size_bytes: int
    damaged: int


NOT_ENTRIES = (".sha256", ".tmp", ".lock")
"""The files of a cache folder that are no entry of it: checksum sidecars, copies being
written, and the locks of models claimed (``<key>.pt.lock``: left behind, empty)."""


def cache_info(root: Path) -> list[CacheKind]:
    """What the cache at ``root`` holds, kind by kind (empty if it does not exist)."""
    kinds = []
    for folder in sorted(p for p in Path(root).glob("*") if p.is_dir()):
        entries = [p for p in folder.iterdir() if p.is_file() and not p.name.endswith(NOT_ENTRIES)]
        damaged = sum(not _intact(p) for p in entries)
        size = sum(p.stat().st_size for p in folder.iterdir() if p.is_file())
        kinds.append(CacheKind(folder.name, len(entries), size, damaged))
    return kinds


def clear_cache(root: Path) -> int:
    """Delete the cache at ``root``; returns the number of bytes freed."""
    root = Path(root)
    if not root.exists():
        return 0
    freed = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    shutil.rmtree(root)
    return freed


RESUME_KIND = "kkl-resume"
"""The kind of the checkpoints of trainings under way (:mod:`kkl_bench.kkl.optimize` writes
them under it; :func:`carry_models` carries them only when asked)."""


@dataclass(frozen=True)
class Carried:
    """What :func:`carry_models` did: models copied (and their bytes), models the destination
    already held, files it left (damaged, or still being written: no matching sidecar), and
    the destination's checkpoints it removed (trainings the source no longer has under way)."""

    copied: int
    size_bytes: int
    present: int
    left: int
    dropped: int = 0


def carry_models(
    source: Path, destination: Path, checkpoints: bool = False, snapshot: bool = False
) -> Carried:
    """Copy the trained models of the cache at ``source`` into ``destination`` (another
    cache, or a folder that travels to another machine), never over an intact model there.

    A model is a ``<kind>/<key>.pt`` file whose SHA-256 sidecar matches its bytes; it is
    copied under a temporary name and renamed, then its sidecar, so an interrupted copy
    leaves at most a file without a sidecar, which the cache would rebuild instead of
    loading and the next copy replaces (as it replaces any damaged file; an intact one
    stays, even where it differs: a model of the same key trained on another machine).
    The checkpoints of trainings under way (:data:`RESUME_KIND`) are carried only with
    ``checkpoints``; locks and the kernels generated for one machine (``*.py``) never.

    A checkpoint is not content-keyed: its key names a training, whose state moves on. With
    ``snapshot`` (an export from the cache that trains) the destination's checkpoints become
    the source's: an intact one that differs is replaced, and one whose training the source
    no longer has (finished, its checkpoints removed) is dropped; one the source is still
    writing stays as it was. Without it (an import) an intact checkpoint at the destination
    stays, since a training there may be resuming from it.
    """
    copied = size = present = left = dropped = 0
    for folder in sorted(p for p in Path(source).glob("*") if p.is_dir()):
        resume = folder.name == RESUME_KIND
        if resume and not checkpoints:
            continue
        replace = resume and snapshot
        for model in sorted(folder.glob("*.pt")):
            if not _intact(model):
                left += 1
                continue
            target = Path(destination) / folder.name / model.name
            if _intact(target) and not (replace and _digest(model) != _digest(target)):
                present += 1
                continue
            _copy_with_sidecar(model, target)
            copied += 1
            size += model.stat().st_size
    if checkpoints and snapshot:
        for stale in sorted((Path(destination) / RESUME_KIND).glob("*.pt")):
            if not (Path(source) / RESUME_KIND / stale.name).exists():
                stale.unlink()
                checksum_path(stale).unlink(missing_ok=True)
                dropped += 1
    return Carried(copied, size, present, left, dropped)


def _copy_with_sidecar(model: Path, target: Path) -> None:
    """Copy ``model`` to ``target`` under a temporary name, rename it, then copy its sidecar
    (the old sidecar removed first: a cut copy leaves a file without one, never new bytes
    beside an old file's sidecar)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=target.parent, suffix=".tmp")
    os.close(handle)
    shutil.copyfile(model, temporary)
    checksum_path(target).unlink(missing_ok=True)
    os.replace(temporary, target)
    shutil.copyfile(checksum_path(model), checksum_path(target))


def _digest(path: Path) -> str:
    """The SHA-256 its sidecar records for ``path``."""
    return checksum_path(path).read_text().strip()


def _intact(path: Path) -> bool:
    """Whether ``path`` exists with a SHA-256 sidecar that matches its bytes."""
    checksum = checksum_path(path)
    return path.exists() and checksum.exists() and _digest(path) == sha256_of(path)


def import_generated(source: str, folder: Path, stem: str) -> ModuleType:
    """Import generated ``source`` as a module saved in ``folder`` (a kind of the cache),
    named by ``stem`` and the source's hash with its checksum beside it, so that numba's
    on-disk cache of the functions it compiles serves the next process, and a changed
    source is a new file."""
    name = f"{stem}_{hashlib.sha256(source.encode()).hexdigest()[:16]}"
    if name in sys.modules:
        return sys.modules[name]
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.py"
    if not path.exists() or path.read_text() != source:
        write_atomically(path, source)
        write_atomically(checksum_path(path), sha256_of(path))
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
