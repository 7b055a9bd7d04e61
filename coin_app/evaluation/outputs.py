"""What every command's outputs obey: one writer per output directory, writes that are whole or absent, outputs outside inputs.

* :class:`OutputLock`: an advisory ``fcntl.flock`` on ``<parent>/.<name>.lock`` beside an output
  directory (``train --out``, a sweep's experiment directory, ``report --out``). The kernel
  releases it when its process ends, however it ends, so a lock file left by a dead process is
  stale by construction: the next writer takes it (and says whose it was). A second live writer
  is refused in one line naming the holder's PID and command.
* :func:`write_text_atomic`: a file written to a hidden sibling, flushed to disk, renamed over the
  target; :func:`staged_outputs`: an output's files built in a hidden sibling and swapped in as one set.
* :func:`check_file_output` / :func:`check_dir_output`: an ``--out`` that can be written and is not
  (inside) an input, checked before any work.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shlex
import shutil
import socket
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

LOCK_SUFFIX = ".lock"  # <parent>/.<name>.lock beside the directory it guards
STAGE_MARK = ".staged-"  # <parent>/.<name>.staged-<pid>: outputs being built; .<name>.old-<pid>: the ones they replace
OLD_MARK = ".old-"


def lock_path(directory: Path) -> Path:
    """The lock file of an output directory: a hidden sibling, so the directory itself can be replaced whole."""
    directory = Path(directory).absolute()
    return directory.parent / f".{directory.name}{LOCK_SUFFIX}"


def this_command() -> str:
    """This process's command line as it was typed (``python -m coin_app train ...``)."""
    argv = list(getattr(sys, "orig_argv", sys.argv))
    if argv and Path(argv[0]).name.startswith("python"):
        argv[0] = "python"
    return shlex.join(argv)


def _alive(pid: int) -> bool:
    """Whether a process with this PID exists on this machine."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _holder_record(fd: int, wait_s: float = 2.0) -> dict[str, Any]:
    """The live holder's record; it writes it just after taking the lock, so an empty or dead one is re-read a while."""
    deadline = time.monotonic() + wait_s
    while True:
        record = _read_record(fd)
        pid = record.get("pid")
        elsewhere = record.get("host") not in (None, socket.gethostname())  # another machine's PID cannot be checked here
        if (isinstance(pid, int) and (elsewhere or _alive(pid))) or time.monotonic() >= deadline:
            return record
        time.sleep(0.02)


class OutputLock:
    """The one writer of an output directory (see module doc); reentrant within a process; ``with`` releases it."""

    _held: dict[str, list[Any]] = {}  # lock path -> [fd, count] of the locks this process holds

    def __init__(self, directory: Path, command: str | None = None, what: str = "the output directory", flag: str = "--out"):
        self.directory = Path(directory)
        self.path = lock_path(self.directory)
        self.command = command or this_command()
        self.what, self.flag = what, flag
        self.stale: dict[str, Any] | None = None  # the record of a dead holder this lock replaced, if any

    def acquire(self) -> OutputLock:
        """Take the lock, or a ValueError naming the live holder (PID, command, start); before any work."""
        key = str(self.path)
        if key in self._held:
            self._held[key][1] += 1
            return self
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(
                f"cannot write {self.what} {self.directory}: {exc.strerror or exc}; allowed: a writable path for {self.flag}"
            ) from exc
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                raise ValueError(
                    f"cannot write {self.what} {self.directory}: {exc.strerror or exc}; allowed: a writable path for {self.flag}"
                ) from exc
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _holder_record(fd)
                os.close(fd)
                raise ValueError(
                    f"{self.directory} is being written by PID {holder.get('pid', '?')} on {holder.get('host', '?')} "
                    f"({holder.get('command', 'unknown command')}, since {holder.get('started', '?')}); "
                    f"allowed: wait until it ends, or another {self.flag}"
                ) from None
            try:  # the file may have been unlinked by its last holder between our open and our lock: lock the file on disk
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        previous = _read_record(fd)
        if previous.get("pid"):
            self.stale = previous  # its holder ended without releasing it (killed): the kernel dropped its lock
        record = {"pid": os.getpid(), "host": socket.gethostname(), "command": self.command, "started": time.strftime("%Y-%m-%d %H:%M:%S")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)
        self._held[key] = [fd, 1]
        return self

    def release(self) -> None:
        """Give the lock up (the last release of this process removes the lock file)."""
        key = str(self.path)
        entry = self._held.get(key)
        if entry is None:
            return
        entry[1] -= 1
        if entry[1] > 0:
            return
        del self._held[key]
        with contextlib.suppress(OSError):
            self.path.unlink()  # before unlocking: a waiting writer then re-opens a fresh file (the inode check above)
        os.close(entry[0])

    def stale_note(self) -> str | None:
        """One line about the dead holder whose lock this one replaced, or None."""
        if not self.stale:
            return None
        pid = self.stale.get("pid")
        state = "still exists (a new process with its PID)" if isinstance(pid, int) and _alive(pid) else "is gone"
        return f"note: {self.directory}'s lock of PID {pid} ({self.stale.get('command', '?')}) was stale (that writer {state}); taken over"

    def __enter__(self) -> OutputLock:
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()


def _read_record(fd: int) -> dict[str, Any]:
    """The holder record in a lock file ({} when empty or unreadable)."""
    try:
        data = os.pread(fd, max(4096, os.fstat(fd).st_size), 0)
        record = json.loads(data.decode()) if data else {}
        return record if isinstance(record, dict) else {}
    except (OSError, ValueError):
        return {}


def fsync_dir(path: Path) -> None:
    """Flush a directory's entries (renames) to disk where the OS allows it."""
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


def write_text_atomic(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` whole or not at all: a hidden sibling, fsynced, renamed over ``path``."""
    path = Path(path)
    partial = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        with open(partial, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)
    fsync_dir(path.parent)
    return path


OUTPUTS_INDEX = ".coin_app_outputs.json"  # in an output directory: the entries its last staged build wrote
SWAP_RECORD = "swap.json"  # in .<name>.old-<pid>: what a swap moves (its entries moved aside, the new ones moved in)


@contextlib.contextmanager
def staged_outputs(directory: Path) -> Iterator[Path]:
    """Build an output's entries in a hidden sibling, then swap them into ``directory`` as one set: the entries the last
    build wrote (``OUTPUTS_INDEX``) and any of the same names move aside, the new ones move in. Other files in
    ``directory`` stay. Yields the staging directory.

    On an error in the build nothing in ``directory`` changes. A kill during the swap (renames only) leaves a record
    beside it; the next build first rolls such a swap back, so ``directory`` always holds one build's entries whole.
    """
    directory = Path(directory).absolute()
    parent, name = directory.parent, directory.name
    directory.mkdir(parents=True, exist_ok=True)
    recover_swaps(directory)
    stage = parent / f".{name}{STAGE_MARK}{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    try:
        yield stage
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    new = sorted(p.name for p in stage.iterdir())
    index = directory / OUTPUTS_INDEX
    try:
        previous = [str(n) for n in json.loads(index.read_text())] if index.is_file() else []
    except ValueError:
        previous = []
    old = sorted(n for n in {*previous, *new} if (directory / n).exists() or (directory / n).is_symlink())
    aside = parent / f".{name}{OLD_MARK}{os.getpid()}"
    shutil.rmtree(aside, ignore_errors=True)
    aside.mkdir()
    write_text_atomic(aside / SWAP_RECORD, json.dumps({"old": old, "new": new}))
    for n in old:  # every old entry aside before any new one moves in (recover_swaps relies on this order)
        os.replace(directory / n, aside / n)
    for n in new:
        os.replace(stage / n, directory / n)
    write_text_atomic(index, json.dumps(new))
    shutil.rmtree(aside)
    shutil.rmtree(stage, ignore_errors=True)


def recover_swaps(directory: Path) -> list[str]:
    """Roll back the swaps of killed builds of ``directory`` (their old entries back, their new ones out) and remove their
    staging directories; the names of the swaps rolled back."""
    directory = Path(directory).absolute()
    parent, name = directory.parent, directory.name
    rolled = []
    for aside in sorted(parent.glob(f".{name}{OLD_MARK}*")):
        pid = aside.name.rsplit("-", 1)[-1]
        if pid.isdigit() and int(pid) != os.getpid() and _alive(int(pid)):
            continue  # a build still running (its lock is the guard; this is belt and braces)
        try:
            record = json.loads((aside / SWAP_RECORD).read_text())
        except (OSError, ValueError):
            record = None  # killed before its record was complete: nothing was moved yet
        if record is not None:
            stage = parent / f".{name}{STAGE_MARK}{pid}"
            for n in record["new"]:  # moved in already: out again (all old entries were aside by then)
                if not (stage / n).exists() and ((directory / n).exists() or (directory / n).is_symlink()):
                    if (directory / n).is_dir() and not (directory / n).is_symlink():
                        shutil.rmtree(directory / n)
                    else:
                        (directory / n).unlink()
            for n in record["old"]:
                if (aside / n).exists() or (aside / n).is_symlink():
                    os.replace(aside / n, directory / n)
            rolled.append(aside.name)
        shutil.rmtree(aside, ignore_errors=True)
    for stage in parent.glob(f".{name}{STAGE_MARK}*"):
        pid = stage.name.rsplit("-", 1)[-1]
        if not (pid.isdigit() and int(pid) != os.getpid() and _alive(int(pid))):
            shutil.rmtree(stage, ignore_errors=True)
    return rolled


def within(path: Path, source: Path) -> bool:
    """Whether ``path`` is ``source`` or lies inside it."""
    path, source = Path(path).resolve(), Path(source).resolve()
    return path == source or source in path.parents


def check_outside(out: Path, inputs: Sequence[Path], flag: str = "--out", what: str = "an input it reads") -> None:
    """Refuse an output that is, or is inside, one of the inputs it is made from (``what``: how the message names them)."""
    for source in inputs:
        if within(out, source):
            raise ValueError(f"bad {flag} {out}: it is, or is inside, {what} ({source}); allowed: a path outside {source}")


def check_file_output(out: Path, inputs: Sequence[Path] = (), flag: str = "--out", what: str = "an input it reads") -> None:
    """Refuse, before any work, an output file that is a directory, cannot be created, or is (inside) an input."""
    out = Path(out)
    check_outside(out, inputs, flag, what)
    if out.is_dir():
        raise ValueError(f"bad {flag} {out}: it is a directory; allowed: a file path (e.g. {out / 'results.json'})")
    parent = out.parent if str(out.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
        probe = parent / f".{out.name}.write-test-{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise ValueError(f"cannot write {flag} {out}: {exc.strerror or exc}; allowed: a writable file path") from exc


def check_dir_output(out: Path, inputs: Sequence[Path] = (), flag: str = "--out", what: str = "an input it reads") -> None:
    """Refuse, before any work, an output directory that is a file, cannot be created or written, or is (inside) an input."""
    out = Path(out)
    check_outside(out, inputs, flag, what)
    if out.exists() and not out.is_dir():
        raise ValueError(f"bad {flag} {out}: it is a file; allowed: a directory path")
    where = out if out.is_dir() else out.absolute().parent  # a new directory: its parent must take it (created if missing)
    try:
        where.mkdir(parents=True, exist_ok=True)
        probe = where / f".{out.name}.write-test-{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise ValueError(f"cannot write {flag} {out}: {exc.strerror or exc}; allowed: a writable directory") from exc
