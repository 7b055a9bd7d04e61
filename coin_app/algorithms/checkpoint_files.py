"""The coin_app checkpoint on disk, importable without Ray: file names, metadata, manifest, verification, the atomic save.

A checkpoint is RLlib's directory layout plus ``coin_app.json``: the algorithm, scenario,
scenario overrides and seed, so a checkpoint is self-describing. Its manifest
(``coin_app_manifest.json``, written last) lists every file with its size and SHA-256, the
algorithm, the scenario, a hash of the config and the code version; every loader checks it
(:func:`verify`), so a torn, altered or foreign directory is refused with one line. ``train``
writes a checkpoint to a temporary sibling and renames it into place, keeping the previous
one as ``<name>.prev`` until the new one is complete (:func:`save_checkpoint`), so a kill at
any moment leaves a complete checkpoint under one of the two names (:func:`latest_complete`).
Loading a checkpoint's policy is :mod:`coin_app.algorithms.checkpoints` (with RLlib).
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import shutil
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

META_FILE = "coin_app.json"  # the algorithm, scenario, seed, overrides and env steps of the run
MANIFEST_FILE = "coin_app_manifest.json"  # every file's size and SHA-256, the config hash and the code version
SHARED_MODULE_ID = "shared"  # the one RLModule all agents share (parameter sharing; common.py's glue builds it)

MANIFEST_VERSION = 1  # the manifest format this code writes
READABLE_MANIFEST_VERSIONS = (1,)  # the manifest formats this code reads
SHAPES_KEY = "parameter_shapes"  # coin_app.json: name -> shape of every tensor of the shared module, as saved
MODULE_STATE_FILE = "module_state.pkl"  # the shared module's tensors (RLlib's file, a pickle of numpy arrays)
MODULE_PATH = ("learner_group", "learner", "rl_module", SHARED_MODULE_ID)  # the shared module inside a checkpoint
PARTIAL_SUFFIX = ".partial"  # a checkpoint being written: <parent>/.<name>.partial
PREVIOUS_SUFFIX = ".prev"  # the previous checkpoint, kept until the new one is in place
ACTOR_ONLY = "actor"  # a manifest's "contents" for a checkpoint cut to its metadata and exported actor (coin_app archive)
MODULE_ONLY = "module"  # a manifest's "contents" for a checkpoint cut to its metadata and shared module, critics included
ACTOR_FILE = "actor.pt"  # an actor-only checkpoint's actor: the TorchScript export of the shared module's deterministic actor


def write_metadata(checkpoint: Path, meta: dict[str, Any]) -> None:
    """Store what a checkpoint was trained on next to it."""
    _write_synced(checkpoint / META_FILE, json.dumps(meta, indent=2, default=str))


def _write_synced(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` and flush it to disk."""
    with open(path, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())


def config_hash(meta: dict[str, Any]) -> str:
    """A short hash of what a run was configured with: algorithm, scenario, overrides and scenario config."""
    keys = {k: meta.get(k) for k in ("algo", "scenario", "overrides", "env_config")}
    return hashlib.sha256(json.dumps(keys, sort_keys=True, default=str).encode()).hexdigest()[:16]


def git_commit() -> str:
    """coin_app's git commit (``-dirty`` with uncommitted changes), or ``"unknown"`` outside a git checkout."""
    try:
        root = Path(__file__).resolve().parents[2]
        out = subprocess.run(
            ["git", "-C", str(root), "describe", "--always", "--dirty", "--abbrev=12"], capture_output=True, text=True, timeout=10
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def code_version() -> str:
    """coin_app's package version and git commit, e.g. ``0.1.0+3f2a9c1b7d4e-dirty``."""
    try:
        version = metadata.version("coin_app")
    except metadata.PackageNotFoundError:
        version = "unknown"
    return f"{version}+{git_commit()}"


def _sha256(path: Path) -> str:
    """The file's SHA-256 (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _files(checkpoint: Path) -> list[str]:
    """The checkpoint's files (relative POSIX paths), the manifest left out."""
    return sorted(p.relative_to(checkpoint).as_posix() for p in checkpoint.rglob("*") if p.is_file() and p.name != MANIFEST_FILE)


def write_manifest(checkpoint: Path, meta: dict[str, Any], contents: str | None = None) -> dict[str, Any]:
    """Write the manifest of a complete checkpoint directory (every file's size and SHA-256, what trained it); returns it.

    ``contents``: :data:`ACTOR_ONLY` or :data:`MODULE_ONLY` for an archived copy (absent: a whole checkpoint, as ``train``
    saves it).
    """
    manifest = {
        "format": "coin_app.checkpoint",
        "version": MANIFEST_VERSION,
        "algo": meta.get("algo"),
        "scenario": meta.get("scenario"),
        "config_hash": config_hash(meta),
        "code_version": code_version(),
        "files": {name: {"size": (checkpoint / name).stat().st_size, "sha256": _sha256(checkpoint / name)} for name in _files(checkpoint)},
    } | ({"contents": contents} if contents else {})
    _write_synced(checkpoint / MANIFEST_FILE, json.dumps(manifest, indent=1))
    return manifest


_VERIFIED: dict[tuple[str, int, int], dict[str, Any]] = {}  # (path, manifest mtime_ns, size) -> metadata, per process


def verify(checkpoint: Path) -> dict[str, Any]:
    """The metadata of a complete, unaltered coin_app checkpoint; a ValueError in one line for anything else.

    Refused: a path that is not a directory, a directory without a manifest (not a coin_app
    checkpoint, or torn while being written by a version before manifests), a file missing,
    extra, of another size or checksum than the manifest says, and metadata that is not what the
    manifest was written for (algorithm, scenario, config hash).
    """
    checkpoint = Path(checkpoint)
    if not checkpoint.is_dir():
        hint = _previous_hint(checkpoint)
        raise ValueError(f"checkpoint {checkpoint} does not exist or is not a directory{hint}")
    man_path = checkpoint / MANIFEST_FILE
    actor_only = contents_of(checkpoint) == ACTOR_ONLY
    body = checkpoint / ACTOR_FILE if actor_only else checkpoint.joinpath(*MODULE_PATH)
    if not man_path.is_file() or not (checkpoint / META_FILE).is_file() or not body.exists():
        raise ValueError(
            f"{checkpoint} is not a complete coin_app checkpoint (missing {MANIFEST_FILE}, {META_FILE} or {body.relative_to(checkpoint)}): "
            f"torn during a save, or not written by coin_app's train{_previous_hint(checkpoint)}"
        )
    stat = man_path.stat()
    key = (str(checkpoint.resolve()), stat.st_mtime_ns, stat.st_size)
    if key in _VERIFIED:
        return dict(_VERIFIED[key])
    try:
        manifest = json.loads(man_path.read_text())
        meta = json.loads((checkpoint / META_FILE).read_text())
        files = dict(manifest["files"])
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{checkpoint}: unreadable {MANIFEST_FILE} or {META_FILE} ({exc})") from exc
    version = manifest.get("version")
    if version not in READABLE_MANIFEST_VERSIONS:
        raise ValueError(
            f"checkpoint {checkpoint}: its manifest has format version {version!r}, this code reads version(s) "
            f"{', '.join(map(str, READABLE_MANIFEST_VERSIONS))}; allowed: a checkpoint of this coin_app version, or the coin_app "
            f"that wrote it ({manifest.get('code_version', 'unknown')})"
        )
    present = _files(checkpoint)
    missing = sorted(set(files) - set(present))
    extra = sorted(set(present) - set(files))
    if missing or extra:
        what = f"missing {missing[:3]}" if missing else f"files not in its manifest {extra[:3]}"
        raise ValueError(f"checkpoint {checkpoint} is torn or altered: {what}{_previous_hint(checkpoint)}")
    for name, want in files.items():
        size = (checkpoint / name).stat().st_size
        if size != want["size"]:
            raise ValueError(
                f"checkpoint {checkpoint} is torn or altered: {name} has {size} bytes, its manifest says {want['size']}"
                f"{_previous_hint(checkpoint)}"
            )
        if _sha256(checkpoint / name) != want["sha256"]:
            raise ValueError(f"checkpoint {checkpoint} is torn or altered: {name} fails its SHA-256 check{_previous_hint(checkpoint)}")
    for field_name, value in (("algo", meta.get("algo")), ("scenario", meta.get("scenario")), ("config_hash", config_hash(meta))):
        if manifest.get(field_name) != value:
            raise ValueError(
                f"checkpoint {checkpoint}: {META_FILE} says {field_name} {value!r}, its manifest "
                f"{manifest.get(field_name)!r} (files of two checkpoints mixed)"
            )
    if SHAPES_KEY in meta and not actor_only:
        recorded = {k: tuple(v) for k, v in meta[SHAPES_KEY].items()}
        differ = shape_difference(recorded, module_shapes(checkpoint), "in its metadata", "in its tensors")
        if differ:
            raise ValueError(f"checkpoint {checkpoint}: its tensors are not the network its metadata records ({differ})")
    _VERIFIED[key] = meta
    return dict(meta)


def module_shapes(checkpoint: Path) -> dict[str, tuple[int, ...]]:
    """Name -> shape of every tensor of the shared module saved in ``checkpoint`` (read from its module state file)."""
    path = Path(checkpoint).joinpath(*MODULE_PATH, MODULE_STATE_FILE)
    try:
        with open(path, "rb") as f:
            state = pickle.load(f)
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ImportError) as exc:
        raise ValueError(f"checkpoint {checkpoint}: cannot read its module's tensors ({type(exc).__name__}: {exc})") from exc
    return {str(k): tuple(v.shape) for k, v in state.items() if hasattr(v, "shape")}


def shape_difference(
    there: dict[str, tuple[int, ...]], here: dict[str, tuple[int, ...]], there_name: str = "there", here_name: str = "here"
) -> str | None:
    """None if two networks' tensors have the same names and shapes; else the first difference and how many differ."""
    diff = sorted(k for k in there.keys() | here.keys() if there.get(k) != here.get(k))
    if not diff:
        return None
    k = diff[0]
    return f"{k}: {there.get(k, 'absent')} {there_name}, {here.get(k, 'absent')} {here_name}; {len(diff)} tensor(s) differ"


def _previous_hint(checkpoint: Path) -> str:
    """``"; the previous checkpoint is <path>.prev"`` when one exists beside ``checkpoint``."""
    prev = checkpoint.with_name(checkpoint.name + PREVIOUS_SUFFIX)
    return f"; the previous checkpoint is {prev}" if prev.is_dir() else ""


def latest_complete(checkpoint: Path) -> tuple[Path, dict[str, Any]]:
    """``checkpoint`` if it verifies, else its ``.prev`` (a save interrupted after the rename); the error of ``checkpoint`` if neither."""
    checkpoint = Path(checkpoint)
    try:
        return checkpoint, verify(checkpoint)
    except ValueError as first:
        prev = checkpoint.with_name(checkpoint.name + PREVIOUS_SUFFIX)
        try:
            return prev, verify(prev)
        except ValueError:
            raise first from None


def save_checkpoint(algo: Any, checkpoint: Path, meta: dict[str, Any], atomic: bool = True) -> Path:
    """Save an RLlib algorithm with coin_app metadata and manifest to ``checkpoint``; returns it.

    ``atomic``: written to ``.<name>.partial`` beside it, the old checkpoint renamed to
    ``<name>.prev``, the new one renamed into place, then the old one removed. A kill at any point
    leaves ``checkpoint`` or ``<name>.prev`` complete. ``atomic=False`` writes into ``checkpoint``
    directly (a directory Tune made for this save), the manifest last.
    """
    checkpoint = Path(checkpoint)
    if not atomic:
        algo.save_to_path(str(checkpoint.resolve()))
        meta = meta | {SHAPES_KEY: module_shapes(checkpoint)}
        write_metadata(checkpoint, meta)
        write_manifest(checkpoint, meta)
        return checkpoint
    partial = checkpoint.with_name("." + checkpoint.name + PARTIAL_SUFFIX)
    prev = checkpoint.with_name(checkpoint.name + PREVIOUS_SUFFIX)
    shutil.rmtree(partial, ignore_errors=True)
    algo.save_to_path(str(partial.resolve()))
    meta = meta | {SHAPES_KEY: module_shapes(partial)}
    write_metadata(partial, meta)
    write_manifest(partial, meta)
    if checkpoint.exists():
        if not (checkpoint / MANIFEST_FILE).is_file():  # a torn checkpoint of an earlier version: nothing worth keeping
            shutil.rmtree(checkpoint)
        else:
            shutil.rmtree(prev, ignore_errors=True)
            checkpoint.rename(prev)
    partial.rename(checkpoint)
    _sync_dir(checkpoint.parent)
    shutil.rmtree(prev, ignore_errors=True)
    return checkpoint


def contents_of(checkpoint: Path) -> str | None:
    """A checkpoint's manifest ``contents``: :data:`ACTOR_ONLY` or :data:`MODULE_ONLY` for an archived copy, None for a
    whole checkpoint (or a directory without a readable manifest, which :func:`verify` refuses)."""
    try:
        return json.loads((Path(checkpoint) / MANIFEST_FILE).read_text()).get("contents")
    except (OSError, ValueError, AttributeError):
        return None


def check_resumable(checkpoint: Path) -> None:
    """A ValueError in one line when ``checkpoint`` is an archived copy, which holds no state to train on from."""
    contents = contents_of(checkpoint)
    if contents in (ACTOR_ONLY, MODULE_ONLY):
        what = "exported actor" if contents == ACTOR_ONLY else "policy module"
        raise ValueError(
            f"checkpoint {checkpoint} holds only its metadata and {what} (an archived copy: no replay, optimizer or env-runner "
            "state); allowed: --resume with a whole checkpoint written by train or a sweep"
        )


def _sync_dir(path: Path) -> None:
    """Flush a directory's entries (the renames) to disk where the OS allows it."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def read_metadata(checkpoint: Path) -> dict[str, Any]:
    """The metadata of a checkpoint written by ``train``, after :func:`verify`; a clear error if it is not a complete one."""
    return verify(checkpoint)
