"""The run folder of :func:`~taskvar_torch.train.train`: one run per folder, locked, never silently
reused; an interrupted run leaves a resumable checkpoint (docs/design.md, "Training the heads").

* :class:`RunFolder` creates and locks ``--out`` (:data:`LOCK_NAME`, ``flock``-ed, so a second run
  on the folder is refused), removes the temporary files a killed write left, and refuses a folder
  already holding a run (:func:`run_files`) unless the run continues from a checkpoint inside it or
  ``--overwrite`` removes the old run first.
* :func:`_restore_logs` cuts a resumed run's CSV logs back to its checkpoint's frame, so they equal
  those of an uninterrupted run.
* :class:`_StopSignals` turns the first SIGINT / SIGTERM into "stop after the current batch"; the
  trainer then writes ``checkpoint_<frame>.pt`` and raises :class:`TrainingInterrupted`
  (:func:`_interrupted`) carrying the exact :func:`resume_command`.

Every name is re-exported by :mod:`taskvar_torch.train`.
"""

from __future__ import annotations

import fcntl
import os
import re
import shlex
import shutil
import signal
import threading
from pathlib import Path
from typing import Any

from taskvar_torch.config import atomic_write

# --------------------------------------------------------------------------------------------
# the run folder: one run per folder, locked, never silently reused


LOCK_NAME = ".taskvar.lock"
"""Lock file of a run folder: ``flock``-ed by the run writing there (released by the kernel when
the process dies, even by SIGKILL), holding its pid; removed when the run ends."""
# the baselines' bundles belong to the run they were trained beside (heads.informed, or
# taskvar train-baselines): an overwrite removes them with it, never leaving another run's
_RUN_NAMES = (
    "config.yaml",
    "final.pt",
    "heads.pt",
    "informed.pt",
    "recurrent.pt",
    "logs",
    "heads",
)
_STALE_TMP = re.compile(r"^\..+\.[0-9a-f]{12}\.tmp$")  # config.atomic_write's temporary files


def run_files(out: str | os.PathLike) -> list[Path]:
    """What a training run left in ``out``: ``config.yaml``, ``final.pt``, ``heads.pt``, the
    baselines' ``informed.pt`` and ``recurrent.pt``, ``checkpoint_*.pt``, ``logs/``, ``heads/``
    (snapshots; empty when ``out`` is not a folder)."""
    out = Path(out)
    if not out.is_dir():
        return []
    found = [out / n for n in _RUN_NAMES if (out / n).exists()]
    return found + sorted(out.glob("checkpoint_*.pt"))


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


def _latest_checkpoint(out: Path) -> Path | None:
    """``final.pt`` if present, else the newest ``checkpoint_*.pt`` of ``out``, else ``None``."""
    if (out / "final.pt").is_file():
        return out / "final.pt"
    periodic = sorted(out.glob("checkpoint_*.pt"))
    return periodic[-1] if periodic else None


class RunFolder:
    """The results folder of one run (:func:`train`), held from :meth:`acquire` to :meth:`release`.

    ``acquire`` creates the folder if needed, locks it (a second run on it is refused), removes
    temporary files a killed write left behind, and refuses a folder that already holds a run
    unless ``resume`` names a checkpoint inside it (continue the run) or ``overwrite`` is set (the
    old run's files are removed first). :meth:`abandon` undoes what a run that failed before
    training started wrote: the folder if it created it, else the files of a fresh run.
    """

    def __init__(
        self, out: str | os.PathLike, resume: str | os.PathLike | None, overwrite: bool
    ) -> None:
        self.out = Path(out)
        self.resume = None if resume is None else Path(resume)
        self.overwrite = bool(overwrite)
        self.created = False
        self.fresh = True  # holds no earlier run's files (none, or removed by --overwrite)
        self._fd: int | None = None

    def acquire(self) -> RunFolder:
        out = self.out
        check_output_folder(out)
        self.created = not out.exists()
        try:
            out.mkdir(parents=True, exist_ok=True)
            self._lock()
        except OSError as e:
            self._remove_if_created()
            raise ValueError(
                f"cannot write in --out {str(out)!r} ({e.strerror or e}); choose another --out"
            ) from None
        try:
            for p in out.iterdir():  # a write killed between its temp file and the rename
                if _STALE_TMP.match(p.name) and p.is_file():
                    p.unlink()
            existing = run_files(out)
            continuing = self.resume is not None and self.resume.resolve().parent == out.resolve()
            if existing and self.overwrite:
                for p in existing:
                    shutil.rmtree(p) if p.is_dir() else p.unlink()
            elif existing and not continuing:
                names = ", ".join(p.name for p in existing[:4]) + (
                    ", ..." if len(existing) > 4 else ""
                )
                latest = _latest_checkpoint(out)
                hint = f"continue it with --resume {shlex.quote(str(latest))}, " if latest else ""
                raise ValueError(
                    f"--out {str(out)!r} already holds a run ({names}); {hint}replace it with "
                    "--overwrite, or choose another --out"
                )
            self.fresh = not existing or self.overwrite
        except BaseException:
            self.release()
            raise
        return self

    def _lock(self) -> None:
        path = self.out / LOCK_NAME
        for _ in range(10):  # the file may be unlinked by the run that held it: take the new one
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                pid = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
                os.close(fd)
                raise ValueError(
                    f"--out {str(self.out)!r} is in use by another taskvar run (pid {pid}); wait "
                    "for it to end or choose another --out"
                ) from None
            try:
                same = os.stat(path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
                self._fd = fd
                return
            os.close(fd)
        raise ValueError(f"--out {str(self.out)!r}: could not lock {LOCK_NAME}; try again")

    def release(self) -> None:
        """Remove the lock file and unlock (the lock is held until its file is gone)."""
        if self._fd is None:
            return
        try:
            (self.out / LOCK_NAME).unlink(missing_ok=True)
        finally:
            os.close(self._fd)
            self._fd = None

    def abandon(self) -> None:
        """After a failure before training started: leave nothing of this run behind."""
        self.release()
        if self.created:
            self._remove_if_created()
        elif self.fresh:
            for p in run_files(self.out):
                shutil.rmtree(p) if p.is_dir() else p.unlink()

    def _remove_if_created(self) -> None:
        if self.created and self.out.is_dir():
            shutil.rmtree(self.out, ignore_errors=True)


def _restore_logs(src: Path, out: Path, frame: int) -> None:
    """Write ``out/logs`` as the rows of run folder ``src``'s logs up to ``frame`` (the checkpoint
    a run resumes from): rows a killed or interrupted run logged after it are dropped, so the
    logs of a resumed run equal those of an uninterrupted one. ``src`` may be ``out``."""
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


def _last_checkpoint_note(path: Path | None) -> str:
    """What a stopped run's message says of the checkpoint it leaves on disk."""
    return f"the last checkpoint {str(path)!r} is intact" if path else "no checkpoint was written"


class _StopSignals:
    """While active (main thread only): the first SIGINT or SIGTERM is recorded in ``signum`` for
    the loop to stop after its current batch; a second one raises ``KeyboardInterrupt`` at once."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._old: dict[int, Any] = {}

    def __enter__(self) -> _StopSignals:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt
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
    "RunFolder",
    "TrainingInterrupted",
    "check_output_folder",
    "resume_command",
    "run_files",
]
