"""Results folders: every taskvar command that writes results holds its ``--out`` as one
:class:`ResultsFolder` (docs/reliability.md#results-folders-locked-staged-swapped-whole).

:func:`restore_logs` cuts a resumed run's CSV logs back to its checkpoint's frame;
:class:`StopSignals` turns the first SIGINT / SIGTERM into "stop after the current batch", after
which the trainer writes a checkpoint and raises :class:`TrainingInterrupted` with the exact
:func:`resume_command`.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import os
import re
import secrets
import shlex
import shutil
import signal
import threading
from pathlib import Path
from typing import Any

from taskvar_torch.config import atomic_write
from taskvar_torch.guest import SignalInterrupt

# --------------------------------------------------------------------------------------------
# the results folder: one command per folder, locked, never silently replaced


LOCK_NAME = ".taskvar.lock"
"""Lock file of a results folder: ``flock``-ed by the command writing there (released by the
kernel when the process dies, even by SIGKILL), holding its pid; removed when the command ends."""
RUN_FILES = (
    "config.yaml", "final.pt", "heads.pt", "informed.pt", "blind.pt", "recurrent.pt", "logs",
    "heads", "checkpoint_*.pt",
)  # fmt: skip
"""What a training run writes in its folder (``taskvar train``'s results), the baselines' bundles
included: they belong to the run they were trained beside (``taskvar train-baselines``), and an
overwrite removes them with it, never leaving another run's."""
RESULT_MARKERS = ("metrics.json", "summary.json")
"""Files that make a folder a results folder of ``taskvar eval``, ``experiment`` or ``sweep``
(written last, once the results are complete)."""
_STALE_TMP = re.compile(r"^\..+\.[0-9a-f]{12}\.tmp$")  # config.atomic_write's temporary files
_STAGING = re.compile(r"^\.(?P<name>.+)\.[0-9a-f]{12}\.(staging|replaced)$")


def _present(folder: Path, names: tuple[str, ...]) -> list[Path]:
    """The entries of ``folder`` that ``names`` name (a name with ``*`` is a glob pattern; a
    symbolic link counts, even a dangling one)."""
    if not folder.is_dir():
        return []
    found = [folder / n for n in names if "*" not in n and os.path.lexists(folder / n)]
    return found + [p for n in names if "*" in n for p in sorted(folder.glob(n))]


def run_files(out: str | os.PathLike) -> list[Path]:
    """What a training run left in ``out`` (:data:`RUN_FILES`; empty when ``out`` is not a
    folder)."""
    return _present(Path(out), RUN_FILES)


def remove_path(p: Path) -> None:
    """Remove ``p``: a folder with its contents, a file, or a symbolic link itself (never what
    it points to)."""
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    else:
        p.unlink(missing_ok=True)


def check_output_folder(path: str | os.PathLike, flag: str = "--out") -> None:
    """A one-line ``ValueError`` unless ``path`` is a writable folder or can be created as one."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {str(path)!r} is a file, not a folder; choose another {flag}")
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(
            f"{flag} {str(path)!r} cannot be created: {str(existing)!r} is a file; choose another "
            f"{flag}"
        )
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(
            f"{flag} {str(path)!r} is not writable (no write access to {str(existing)!r}); "
            f"choose another {flag}"
        )


def lock_folder(folder: Path, flag: str = "--out") -> int:
    """``flock`` ``folder/LOCK_NAME`` (created, holding this pid) and return its descriptor; a
    folder locked by another taskvar process is a one-line ``ValueError`` naming its pid."""
    path = folder / LOCK_NAME
    for _ in range(10):  # the file may be unlinked by the run that held it: take the new one
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise ValueError(
                f"{flag} {str(folder)!r} is in use by another taskvar run (pid {pid}); wait "
                f"for it to end or choose another {flag}"
            ) from None
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
            return fd
        os.close(fd)
    raise ValueError(f"{flag} {str(folder)!r}: could not lock {LOCK_NAME}; try again")


def unlock_folder(folder: Path, fd: int) -> None:
    """Undo :func:`lock_folder`: remove the lock file while still holding it (unless it is no
    longer this lock's: a swapped-in folder has none), then close."""
    lock = folder / LOCK_NAME
    try:
        if lock.is_file() and os.stat(lock).st_ino == os.fstat(fd).st_ino:
            lock.unlink()
    finally:
        os.close(fd)


def check_out_path(path: str | os.PathLike, flag: str = "--out") -> Path:
    """``path`` as a :class:`Path`; an empty one (``--out ''``, which would be the current
    folder) is a one-line ``ValueError``."""
    if not str(path).strip():
        raise ValueError(f"{flag} is empty; name where to write (the current folder is {flag} .)")
    _refuse_dangling(Path(path), flag)
    return Path(path)


def _refuse_dangling(path: Path, flag: str) -> None:
    """A one-line ``ValueError`` when ``path`` or a folder above it is a symbolic link to nothing."""
    for p in (path, *path.parents):
        if p.is_symlink() and not p.exists():
            where = "" if p == path else f" (in {flag} {str(path)!r})"
            raise ValueError(
                f"{flag} {str(p)!r}{where} is a dangling symbolic link: it points to "
                f"{os.readlink(p)!r}, which does not exist; create that folder, remove the link, "
                f"or choose another {flag}"
            )


def refuse_inside(source: str | os.PathLike, out: str | os.PathLike, flag: str) -> None:
    """A one-line ``ValueError`` when ``source`` (a file the command reads) is ``out`` or lies
    inside it: writing the results would replace or remove it."""
    src, dest = Path(source).resolve(), Path(out).resolve()
    if src == dest or dest in src.parents:
        raise ValueError(
            f"{flag} {str(source)!r} lies in --out {str(out)!r}: writing the results there would "
            "remove it; choose another --out"
        )


def _holds_a_run(out: Path) -> bool:
    """Whether the run files of ``out`` are a taskvar run's: a checkpoint, CSV logs, or a
    ``config.yaml`` that loads as a taskvar config (what ``--overwrite`` may remove)."""
    if any((out / n).is_file() for n in ("final.pt", "heads.pt")) or any(
        out.glob("checkpoint_*.pt")
    ):
        return True
    if (out / "logs" / "scalars").is_dir() and not (out / "logs").is_symlink():
        return True
    from taskvar_torch.config import load_config

    try:
        load_config(out / "config.yaml")
    except (ValueError, OSError):
        return False
    return True


def _latest_checkpoint(out: Path) -> Path | None:
    """``final.pt`` if present, else the newest ``checkpoint_*.pt`` of ``out``, else ``None``."""
    if (out / "final.pt").is_file():
        return out / "final.pt"
    periodic = sorted(out.glob("checkpoint_*.pt"))
    return periodic[-1] if periodic else None


class ResultsFolder:
    """The results folder ``out`` of one taskvar command, held from :meth:`acquire` to
    :meth:`commit` (or :meth:`abandon`); a context manager that commits on success, else abandons.

    :meth:`acquire` refuses an unusable ``out`` and results already there (``markers``, glob
    patterns) unless ``overwrite``, creates and locks it (:func:`lock_folder`) and removes killed
    writes' temporary files. ``staged=True``: returns an empty sibling ``.<name>.<hex>.staging``
    that :meth:`commit` swaps in for ``out`` whole (a folder holding non-taskvar files is refused).
    ``staged=False``: returns ``out``, written in place; ``overwrite`` removes the marker entries,
    ``resume`` continues them. ``command``, ``hint`` and ``flag`` go into the refusals.
    """

    def __init__(
        self,
        out: str | os.PathLike,
        overwrite: bool = False,
        command: str = "",
        markers: tuple[str, ...] | None = None,
        *,
        staged: bool = True,
        resume: str | os.PathLike | None = None,
        hint: str = "",
        flag: str = "--out",
    ) -> None:
        self.out = check_out_path(out, flag)
        self.overwrite = bool(overwrite)
        self.command = command
        self.markers = (RESULT_MARKERS if staged else ()) if markers is None else markers
        self.staged = staged
        self.continuing = resume is not None and Path(resume).resolve().parent == self.out.resolve()
        self.hint = hint
        self.flag = flag
        self.staging: Path | None = None
        self.created = False
        self.fresh = False  # in place: held no earlier results (none, or removed by overwrite)
        self._fd: int | None = None

    def check(self) -> None:
        """The refusals of :meth:`acquire`, without touching anything."""
        out, flag = self.out, self.flag
        check_output_folder(out, flag)
        found = _present(out, self.markers)
        entries = _visible_entries(out) if self.staged else found  # staged: out is the whole
        if entries and not found:
            raise ValueError(
                f"{flag} {str(out)!r} holds files that are not taskvar results "
                f"({_names(entries)}); choose an empty or new folder ({self.command})"
            )
        if not entries or self.continuing:
            return
        if not self.overwrite:
            latest = None if self.staged else _latest_checkpoint(out)
            hint = f"continue it with --resume {shlex.quote(str(latest))}, " if latest else ""
            what, it = ("results", "them") if self.staged else ("a run", "it")
            raise ValueError(
                f"{flag} {str(out)!r} already holds {what} ({_names(entries)}); "
                f"{self.hint or hint}replace {it} with --overwrite, or choose another {flag}"
                + (f" ({self.command})" if self.command else "")
            )
        if not self.staged and not _holds_a_run(out):  # e.g. --out . with a project's config.yaml
            raise ValueError(
                f"{flag} {str(out)!r} holds {_names(entries)} but no taskvar run (no checkpoint, "
                f"logs or taskvar config); --overwrite removes only a run's files: choose another "
                f"{flag}"
            )

    def acquire(self) -> Path:
        """Check, create, lock and check again; return the folder to write into: the empty
        staging folder, or ``out`` itself (its earlier results removed with ``overwrite``)."""
        self.check()
        out = self.out
        self.created = not out.exists()
        try:
            out.mkdir(parents=True, exist_ok=True)
            self._fd = lock_folder(out, self.flag)
        except OSError as e:
            self._remove_if_created()
            raise ValueError(
                f"cannot write in {self.flag} {str(out)!r} ({e.strerror or e}); choose another "
                f"{self.flag}"
            ) from None
        except BaseException:
            self._remove_if_created()
            raise
        try:
            for p in out.iterdir():  # a write killed between its temp file and the rename
                if _STALE_TMP.match(p.name) and p.is_file():
                    p.unlink()
            self.check()  # again, under the lock: another command may have written meanwhile
            if self.staged:
                self.staging = self._stage()
                return self.staging
            earlier = _present(out, self.markers)
            self.fresh = not earlier or self.overwrite
            if self.overwrite:
                for p in earlier:
                    remove_path(p)
        except BaseException:
            self.abandon()
            raise
        return out

    def _stage(self) -> Path:
        """A new empty staging folder beside ``out``, once a killed command's are removed."""
        out = self.out.resolve()
        if out.stat().st_dev != out.parent.stat().st_dev:
            raise ValueError(
                f"{self.flag} {str(self.out)!r} is a mount point: its results are swapped in from "
                "a sibling folder; choose a folder inside it"
            )
        for p in out.parent.iterdir():  # what a killed command on this folder left
            m = _STAGING.match(p.name)
            if m and m["name"] == out.name and m[2] == "staging" and p.is_dir():
                shutil.rmtree(p, ignore_errors=True)  # (a ".replaced" one is kept: commit)
        staging = out.parent / f".{out.name}.{secrets.token_hex(6)}.staging"
        staging.mkdir()
        return staging

    def commit(self) -> None:
        """Keep what was written: swap the staging folder in for ``out`` (the old results removed
        after), then unlock."""
        staging, out = self.staging, self.out.resolve()
        try:
            if staging is not None:
                if not _exchange(staging, out):  # no atomic exchange here: two renames (killed
                    # between them, the old results stay in .<name>.<hex>.replaced, never removed)
                    old = staging.with_name(staging.name[: -len(".staging")] + ".replaced")
                    os.rename(out, old)
                    os.rename(staging, out)
                    staging = old
                shutil.rmtree(staging, ignore_errors=True)  # the old results and the lock file
        finally:
            self.staging = None
            self._unlock()

    def abandon(self) -> None:
        """Leave ``out`` as it was: remove the staging folder, or in place what this command
        wrote where no results were; unlock; remove ``out`` if this command created it."""
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging = None
        self._unlock()
        if self.fresh:
            for p in _present(self.out, self.markers):
                remove_path(p)
        self._remove_if_created()

    def _unlock(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            unlock_folder(self.out, fd)

    def _remove_if_created(self) -> None:
        if self.created and self.out.is_dir() and not _visible_entries(self.out):
            shutil.rmtree(self.out, ignore_errors=True)

    def __enter__(self) -> Path:
        return self.acquire()

    def __exit__(self, kind: Any, error: Any, *exc: Any) -> None:
        if kind is None:
            self.commit()
            return
        staging = self.staging
        self.abandon()
        if staging is None:
            return
        if isinstance(error, OSError) and error.filename:
            try:  # the file as the user knows it: in --out, not in the staging folder removed
                rel = Path(error.filename).relative_to(staging)
                error.filename = str(self.out / rel)
            except ValueError:
                pass
        if isinstance(error, TrainingInterrupted):  # its checkpoint was in the staging folder
            name = signal.Signals(error.signum).name
            raise TrainingInterrupted(
                f"interrupted by {name}; nothing written: {self.flag} {str(self.out)!r} holds "
                "what it held before",
                None,
                None,
                error.signum,
            ) from None


def _names(paths: list[Path]) -> str:
    """The first four names of ``paths``, sorted, for a one-line message."""
    return ", ".join(sorted(p.name for p in paths)[:4]) + (", ..." if len(paths) > 4 else "")


def _visible_entries(folder: Path) -> list[Path]:
    """What ``folder`` holds besides its lock file and temporary files of killed writes."""
    if not folder.is_dir():
        return []
    return [
        p
        for p in folder.iterdir()
        if p.name != LOCK_NAME and not _STALE_TMP.match(p.name) and not _STAGING.match(p.name)
    ]


def _exchange(a: Path, b: Path) -> bool:
    """Atomically exchange folders ``a`` and ``b`` (Linux ``renameat2(RENAME_EXCHANGE)``);
    ``False`` where the system or file system has no such call (nothing changed then)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    renameat2.argtypes = [
        ctypes.c_int,
        ctypes.c_char_p,
        ctypes.c_int,
        ctypes.c_char_p,
        ctypes.c_uint,
    ]
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def restore_logs(src: Path, out: Path, frame: int) -> None:
    """Write ``out/logs`` as run folder ``src``'s logs up to ``frame``, so a resumed run's logs
    equal an uninterrupted one's (``src`` may be ``out``).
    """
    scalars = src / "logs" / "scalars"
    if not scalars.is_dir():
        return
    for f in sorted(scalars.glob("*.csv")):
        kept = []
        for line in f.read_text().splitlines(keepends=True):
            step = line.split(",", 1)[0]
            if line.endswith("\n") and step.isdigit() and int(step) <= frame:
                kept.append(line)
        text = "".join(kept).encode()
        atomic_write(out / "logs" / "scalars" / f.name, lambda h, text=text: h.write(text))


# --------------------------------------------------------------------------------------------
# interruption: SIGINT / SIGTERM stop the run after its batch, at a resumable checkpoint


class TrainingInterrupted(RuntimeError):
    """SIGINT or SIGTERM stopped the run after its current batch; ``checkpoint`` holds the state
    (``None`` when the weights were not finite), ``resume_command`` continues it."""

    def __init__(
        self, message: str, checkpoint: Path | None, resume_command: str | None, signum: int
    ):
        super().__init__(message)
        self.checkpoint = checkpoint
        self.resume_command = resume_command
        self.signum = signum


def last_checkpoint_note(path: Path | None) -> str:
    """What a stopped run's message says of the checkpoint it leaves on disk."""
    return f"the last checkpoint {str(path)!r} is intact" if path else "no checkpoint was written"


class StopSignals:
    """While active (main thread only): the first SIGINT or SIGTERM is recorded in ``signum`` for
    the loop to stop after its current batch; a second one raises ``KeyboardInterrupt`` at once."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._old: dict[int, Any] = {}

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is not None:
            raise SignalInterrupt(signum)  # a signal's, not one a family's code raised
        self.signum = signum

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self._old.items():
            signal.signal(sig, handler)
        self._old.clear()


def resume_command(checkpoint: Path, out: Path) -> str:
    """The ``taskvar train`` command line continuing a run from ``checkpoint`` in ``out``."""
    return f"taskvar train --resume {shlex.quote(str(checkpoint))} --out {shlex.quote(str(out))}"


def _interrupted(
    signum: int, checkpoint: Path, out: Path, counters: dict[str, int], remote: bool
) -> TrainingInterrupted:
    """The one-line report of a run stopped by ``signum`` after writing ``checkpoint``."""
    name = signal.Signals(signum).name
    head = f"interrupted by {name} at frame {counters['frames']}; saved {str(checkpoint)!r}"
    if remote:
        return TrainingInterrupted(
            f"{head} (a run with collector workers cannot be resumed; evaluate it with taskvar "
            f"eval --checkpoint {shlex.quote(str(checkpoint))})",
            checkpoint,
            None,
            signum,
        )
    command = resume_command(checkpoint, out)
    return TrainingInterrupted(f"{head}; continue with: {command}", checkpoint, command, signum)


__all__ = [
    "LOCK_NAME",
    "RUN_FILES",
    "ResultsFolder",
    "TrainingInterrupted",
    "check_out_path",
    "check_output_folder",
    "resume_command",
    "run_files",
]
