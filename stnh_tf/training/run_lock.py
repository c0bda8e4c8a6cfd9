"""The lock of a training run's folder (:class:`RunLock`): one run at a time in a ``model_dir``
(:mod:`stnh_tf.training.run_dir` re-exports both names)."""

from __future__ import annotations

import os

LOCK_FILE = ".stnh_tf_run.lock"
"""The lock file of a run's folder (:class:`RunLock`); not part of the run (never deleted by
:func:`~stnh_tf.training.run_dir.remove_run`, ignored when a folder is checked for being
empty)."""


class RunLock:
    """The lock of a training run's folder: one run at a time in ``model_dir``.

    Made before :func:`~stnh_tf.training.run_dir.prepare_model_dir` and released when the run
    ends (:meth:`release`, or as a context manager), it holds ``fcntl.flock`` on
    ``model_dir/.stnh_tf_run.lock`` (:data:`LOCK_FILE`; ``model_dir`` is created if missing). A
    second run in the same folder, in this process or another, is refused at once, before it
    reads or deletes anything there; the lock goes with the process, so a killed run leaves none
    held. The lock file is removed on release if this lock created it (a stale one left by a
    killed run stays, and is reused).

    ``busy``: the refusal when another holds the lock, a format string of ``folder`` and ``lock``
    (the lock file); by default it names ``model_dir``.

    Raises:
      FileExistsError: another run holds the lock (``busy``: the message names the folder).
      NotADirectoryError: ``model_dir`` exists and is not a folder.
      PermissionError: ``model_dir`` cannot be created or written.
    """

    BUSY = ("another training run is using model_dir {folder} (it holds {lock}); wait for it to "
            "finish, or choose another --model_dir.")

    def __init__(self, model_dir: str, busy: str = BUSY):
        import fcntl

        self.model_dir = os.fspath(model_dir)
        self.path = os.path.join(self.model_dir, LOCK_FILE)
        if os.path.exists(self.model_dir) and not os.path.isdir(self.model_dir):
            raise NotADirectoryError(f"model_dir {self.model_dir} exists and is not a folder.")
        self.made_dir = not os.path.exists(self.model_dir)
        self._fd = None
        try:
            os.makedirs(self.model_dir, exist_ok=True)
            for _ in range(10):  # retried only when the holder removed the file meanwhile
                try:
                    fd, self.created = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL,
                                               0o644), True
                except FileExistsError:
                    try:
                        fd, self.created = os.open(self.path, os.O_RDWR), False
                    except FileNotFoundError:
                        continue
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    os.close(fd)
                    raise FileExistsError(busy.format(folder=self.model_dir,
                                                      lock=self.path)) from None
                if self._same_file(fd):
                    self._fd = fd
                    return
                os.close(fd)  # locked a file its holder had just removed: try again
        except PermissionError:
            raise PermissionError(f"model_dir {self.model_dir} is not writable.") from None
        raise FileExistsError(f"cannot lock model_dir {self.model_dir}: {self.path} keeps being "
                              "replaced by another process.")

    def _same_file(self, fd) -> bool:
        try:
            return os.stat(self.path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            return False

    def release(self) -> None:
        """Unlock (idempotent); remove the lock file if this lock created it, and ``model_dir``
        if this lock created it and nothing else is in it."""
        if self._fd is None:
            return
        try:
            if self.created and self._same_file(self._fd):
                os.remove(self.path)
        finally:
            os.close(self._fd)  # releases the flock
            self._fd = None
        if self.made_dir and os.path.isdir(self.model_dir) and not os.listdir(self.model_dir):
            os.rmdir(self.model_dir)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()
