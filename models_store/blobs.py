"""The blob store: immutable files and directories under one local root, checksummed.

A blob is a file (an uploaded mesh, a clip, an artifact) or a directory (a trained model:
``manifest.json`` + ``.npz`` + ``.exr``), stored under a caller-chosen key such as
``actors/act_…/clips/clp_….npz`` or ``models/mdl_…/01j9…``. The database keeps each blob's
key and sha256; reading a blob back verifies it and raises
:class:`~models_store.errors.BlobCorrupt` on a mismatch.

Writes are atomic: a file is written to a temporary sibling, fsynced, chmodded, renamed into
place (:func:`models_store.atomic.atomic_open`), and its directory fsynced; a directory is
copied under a temporary sibling name, every file and directory in it fsynced, then renamed
into place in one step. Readers in other processes therefore see a whole blob or none.
Blobs are write-once: putting to an existing key raises
:class:`~models_store.errors.Conflict` (callers make keys unique, e.g. with
:func:`models_store.ids.new_token`).

Files get mode 0644 and directories 0755 whatever the umask, so workers running as another
user can read them (``atomic_open``'s ``mkstemp`` alone would leave 0600).

Keys are ``/``-separated segments of ``[A-Za-z0-9._-]`` each starting with a letter or
digit: no absolute paths, no ``..``, no hidden names (temporary names start with a dot, so
they can never collide with a key).

Temporaries — the siblings of blobs being written, directories being deleted, the scratch
directories of jobs (:meth:`BlobStore.scratch_dir`) — are the hidden names. A crash (a
SIGKILLed worker or API) leaves them behind; :meth:`BlobStore.sweep_temporaries` removes
those older than an age, and never a scratch directory still in use: its owner holds an
exclusive ``flock`` on it for as long as it lives, which the kernel releases when the owner
dies however it dies. :meth:`BlobStore.health` tells whether the store can be written and
how much space is free (for ``/readyz``).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import io
import os
import re
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

from models_store.errors import BlobCorrupt, Conflict, InvalidId, NotFound
from models_store.ids import new_token
from models_store.atomic import atomic_open, sha256_file

FILE_MODE = 0o644
DIR_MODE = 0o755
CHUNK = 1 << 20
MAX_KEY_LENGTH = 512
_SEGMENT = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


class VerifiedDir(type(Path())):  # type: ignore[misc]  # PosixPath / WindowsPath
    """The path of a directory blob whose files were just verified (:meth:`BlobStore.open_dir`).

    ``digests`` maps each file's relative POSIX path to the sha256 hex digest of its content
    as read during that verification (the tree digest the database records is made of
    them): a reader that checks the files against a manifest of its own
    (:func:`service.methods.model_dir.read_model_files`) compares with these instead of
    hashing the whole directory a second time (issue 23: 0.36 s of a level-1 PDM's load).
    Paths derived from it (``path / name``) are plain paths without digests.
    """

    digests: dict[str, str]

    @classmethod
    def of(cls, path: str | os.PathLike[str], digests: dict[str, str]) -> VerifiedDir:
        """``path`` with ``digests`` (constructed with the path alone: ``Path.__init__``
        takes the constructor's arguments from Python 3.12 on)."""
        verified = cls(path)
        verified.digests = dict(digests)
        return verified


class VerifyingDir(VerifiedDir):
    """The path of a directory blob whose files are being verified in a background thread
    while the caller reads them (:meth:`BlobStore.open_dir` with ``background=True``).

    A model's load then overlaps the hashing of its files instead of waiting for it (issue
    23: 0.36 s of a level-1 PDM's 0.8 s load; ``hashlib`` and file reads release the GIL).
    Nothing read from it may be used before :meth:`confirm` returns: a file that does not
    match fails there (:class:`~models_store.errors.BlobCorrupt`), and so does any check a
    reader deferred with :meth:`after_verify`. ``digests`` waits for the thread.
    """

    _thread: threading.Thread
    _result: dict
    _checks: list

    @classmethod
    def start(cls, path: Path, key: str, sha256: str) -> VerifyingDir:
        """``path`` with its verification against the tree digest ``sha256`` running."""
        pending = cls(path)
        pending._result, pending._checks = {}, []

        def verify() -> None:
            try:
                digests = {rel: sha256_file(src) for src, rel in _walk_files(path)}
                _check(key, sha256, tree_digest(digests))
                pending._result["digests"] = digests
            except BaseException as error:  # noqa: BLE001 - re-raised by confirm()
                pending._result["error"] = error

        pending._thread = threading.Thread(target=verify, name=f"verify-{path.name}", daemon=True)
        pending._thread.start()
        return pending

    @property
    def digests(self) -> dict[str, str]:  # type: ignore[override]
        self._thread.join()
        if "error" in self._result:
            raise self._result["error"]
        return self._result["digests"]

    def after_verify(self, check: Callable[[dict[str, str]], None]) -> None:
        """Run ``check(digests)`` in :meth:`confirm`, once the files are verified."""
        self._checks.append(check)

    def confirm(self) -> None:
        """Wait for the verification; raise what it found (BlobCorrupt, NotFound, OSError),
        then what the deferred checks raise."""
        digests = self.digests
        for check in self._checks:
            check(digests)


class ScratchFile(os.PathLike):
    """A finished file in the store's scratch space (:meth:`BlobStore.scratch_dir`), given
    as a blob's content: the registry moves it into place (``put_file(..., move=True)``)
    instead of copying it, so a large upload is written once (issue 16, defect 11)."""

    def __init__(self, path: str | os.PathLike[str]):
        self.path = Path(path)

    def __fspath__(self) -> str:
        return str(self.path)

    def __repr__(self) -> str:
        return f"ScratchFile({str(self.path)!r})"


@dataclass(frozen=True)
class BlobInfo:
    """What was stored: the key, the sha256 hex digest and the size in bytes.

    For a directory, ``sha256`` is the tree digest (:func:`tree_digest`) and ``size`` the
    total size of its files.
    """

    key: str
    sha256: str
    size: int


def validate_key(key: object) -> str:
    """Return ``key`` if it is a well-formed blob key, else raise :class:`InvalidId`."""
    if not isinstance(key, str) or not key or len(key) > MAX_KEY_LENGTH:
        raise InvalidId(f"blob key {key!r} must be a non-empty string of at most "
                        f"{MAX_KEY_LENGTH} characters")
    bad = [s for s in key.split("/") if not _SEGMENT.fullmatch(s)]
    if bad:
        raise InvalidId(f"blob key {key!r} has an invalid segment {bad[0]!r}: segments are "
                        "[A-Za-z0-9._-], start with a letter or digit, at most 128 characters")
    return key


def tree_digest(entries: dict[str, str]) -> str:
    """sha256 of a directory from its files' digests.

    Parameters
    ----------
    entries : dict   relative POSIX path → sha256 hex digest of that file

    Returns
    -------
    str   sha256 hex digest of the lines ``"<sha256>  <path>\\n"`` sorted by path (the
          format of ``sha256sum``), so ``sha256sum`` can reproduce it
    """
    lines = "".join(f"{entries[p]}  {p}\n" for p in sorted(entries))
    return hashlib.sha256(lines.encode()).hexdigest()


@dataclass(frozen=True)
class StoreHealth:
    """Whether the blob store can take writes: :meth:`BlobStore.health`.

    Attributes
    ----------
    writable : bool     a probe file could be created, written, fsynced and removed
    free_bytes : int    space available to this process (``statvfs`` ``f_bavail``)
    total_bytes : int   size of the filesystem
    reason : str        why the store is not ready ("" when it is); no server paths
    """

    writable: bool
    free_bytes: int
    total_bytes: int
    reason: str = ""

    @property
    def ready(self) -> bool:
        return not self.reason


class BlobStore:
    """Blobs in a local directory (see the module docstring).

    Parameters
    ----------
    root : str | Path   directory of the store; created if missing
    """

    def __init__(self, root: str | os.PathLike[str]):
        self.root = Path(root).absolute()
        if not self.root.is_dir():
            self.root.mkdir(parents=True, exist_ok=True)
            os.chmod(self.root, DIR_MODE)

    def __repr__(self) -> str:
        return f"BlobStore({str(self.root)!r})"

    # -- paths ---------------------------------------------------------------------------
    def path(self, key: str) -> Path:
        """The filesystem path of ``key`` (whether or not it exists)."""
        return self.root.joinpath(*validate_key(key).split("/"))

    def exists(self, key: str) -> bool:
        """Whether a blob is stored under ``key``."""
        return self.path(key).exists()

    # -- writing -------------------------------------------------------------------------
    def put_bytes(self, key: str, data: bytes) -> BlobInfo:
        """Store ``data`` as a file blob."""
        return self._put_stream(key, io.BytesIO(data))

    def put_file(self, key: str, source: str | os.PathLike[str], move: bool = False) -> BlobInfo:
        """Store a copy of the file ``source`` as a file blob; with ``move``, store the file
        itself: it is fsynced, hashed (read in chunks) and renamed into place, so a file
        already written in the store's scratch space (:meth:`scratch_dir`, the same
        filesystem) is stored without a second copy (it is copied if it is elsewhere)."""
        if not move:
            with open(source, "rb") as stream:
                return self._put_stream(key, stream)
        final = self._vacant(key)
        with open(source, "rb") as stream:
            os.fchmod(stream.fileno(), FILE_MODE)
            os.fsync(stream.fileno())
            sha256, size = _digest(stream)
        try:
            os.rename(source, final)
        except OSError as error:
            if error.errno != errno.EXDEV:
                raise
            with open(source, "rb") as stream:
                return self._put_stream(key, stream)
        _fsync_dir(final.parent)
        return BlobInfo(key, sha256, size)

    def put_dir(self, key: str, source: str | os.PathLike[str]) -> BlobInfo:
        """Store a copy of the directory tree ``source`` as a directory blob.

        Raises
        ------
        ValueError   if ``source`` is not a directory or contains a symbolic link
        Conflict     if ``key`` is taken
        """
        source = Path(source)
        if not source.is_dir():
            raise ValueError(f"{source} is not a directory")
        final = self._vacant(key)
        tmp = self._temporary_sibling(final)
        entries: dict[str, str] = {}
        size = 0
        try:
            _make_dir(tmp)
            for src, rel in _walk_files(source):
                dst = tmp.joinpath(*rel.split("/"))
                self._make_parents(dst, stop=tmp)
                with open(src, "rb") as fin, _create(dst) as fout:
                    entries[rel], n = _copy(fin, fout)
                size += n
            for directory in sorted((p for p in tmp.rglob("*") if p.is_dir()), reverse=True):
                _fsync_dir(directory)
            _fsync_dir(tmp)
            if final.exists():
                raise Conflict(f"blob key {key!r} is already taken")
            os.rename(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        _fsync_dir(final.parent)
        return BlobInfo(key, tree_digest(entries), size)

    def _put_stream(self, key: str, stream: BinaryIO) -> BlobInfo:
        final = self._vacant(key)
        with atomic_open(final) as out:
            os.fchmod(out.fileno(), FILE_MODE)
            sha256, size = _copy(stream, out)
        _fsync_dir(final.parent)
        return BlobInfo(key, sha256, size)

    def _vacant(self, key: str) -> Path:
        """The path for a new blob at ``key``, with its parent directories made."""
        final = self.path(key)
        if final.exists():
            raise Conflict(f"blob key {key!r} is already taken; blobs are write-once")
        self._make_parents(final, stop=self.root)
        return final

    @staticmethod
    def _make_parents(path: Path, stop: Path) -> None:
        """Create the missing directories between ``stop`` and ``path``'s parent (0755)."""
        missing = [p for p in path.relative_to(stop).parents if not (stop / p).is_dir()]
        for rel in reversed(missing):
            _make_dir(stop / rel)

    @staticmethod
    def _temporary_sibling(path: Path) -> Path:
        return path.with_name(f".{path.name}.{new_token()}.tmp")

    # -- reading -------------------------------------------------------------------------
    def read_bytes(self, key: str, sha256: str) -> bytes:
        """The content of a file blob, verified against ``sha256``.

        Raises
        ------
        NotFound      no file blob under ``key``
        BlobCorrupt   the content does not match ``sha256``
        """
        try:
            data = self._file(key).read_bytes()
        except FileNotFoundError:            # deleted between the check and the read
            raise NotFound("blob", key) from None
        _check(key, sha256, hashlib.sha256(data).hexdigest())
        return data

    def open(self, key: str, sha256: str) -> BinaryIO:
        """A binary file object on a file blob, positioned at the start, after verifying the
        whole file against ``sha256`` (the caller closes it).

        Raises
        ------
        NotFound, BlobCorrupt   as :meth:`read_bytes`
        """
        path = self._file(key)
        _check(key, sha256, sha256_file(path))
        return open(path, "rb")  # blobs are write-once: what was verified is what is read

    def open_dir(self, key: str, sha256: str, background: bool = False) -> VerifiedDir:
        """The path of a directory blob after verifying every file against ``sha256`` (the
        tree digest returned by :meth:`put_dir`), with the digests of its files as verified
        (:class:`VerifiedDir`: a reader of the files' own manifest compares against those
        instead of hashing every file again).

        ``background``: return at once, verifying in a thread (:class:`VerifyingDir`; the
        caller must :meth:`~VerifyingDir.confirm` before it uses what it read).

        Raises
        ------
        NotFound, BlobCorrupt   as :meth:`read_bytes` (with ``background``: NotFound only;
                                the rest from ``confirm``)
        """
        path = self.path(key)
        if not path.is_dir():
            raise NotFound("blob directory", key)
        if background:
            return VerifyingDir.start(path, key, sha256)
        digests = {rel: sha256_file(src) for src, rel in _walk_files(path)}
        _check(key, sha256, tree_digest(digests))
        return VerifiedDir.of(path, digests)

    def digest(self, key: str) -> str:
        """The sha256 of what is stored under ``key`` now (file digest or tree digest)."""
        path = self.path(key)
        if path.is_dir():
            return tree_digest({rel: sha256_file(src) for src, rel in _walk_files(path)})
        if path.is_file():
            return sha256_file(path)
        raise NotFound("blob", key)

    def _file(self, key: str) -> Path:
        path = self.path(key)
        if not path.is_file():
            raise NotFound("blob", key)
        return path

    # -- scratch space, temporaries, health --------------------------------------------------
    @contextlib.contextmanager
    def scratch_dir(self, prefix: str) -> Iterator[Path]:
        """A new hidden scratch directory ``.<prefix>-<token>`` in the store's root (the same
        filesystem as the blobs, so a finished result is stored by a rename or a local copy),
        removed when the block ends however it ends.

        While the block runs the directory is locked (``flock``), so
        :meth:`sweep_temporaries` never removes it, however old it is.
        """
        if not re.fullmatch(r"[a-z][a-z0-9-]{0,40}", prefix):
            raise ValueError(f"scratch prefix {prefix!r} must be lowercase letters, digits, -")
        path = self.root / f".{prefix}-{new_token()}"
        os.mkdir(path, DIR_MODE)
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield path
        finally:
            shutil.rmtree(path, ignore_errors=True)
            os.close(fd)

    def sweep_temporaries(self, older_than: float, now: float | None = None) -> list[str]:
        """Remove the temporaries a crash left behind; their paths relative to the root.

        A temporary is any hidden name (``.…``) in the store: the siblings of blobs being
        written, directories being deleted, job scratch directories. One is removed when
        nothing in it was modified for ``older_than`` seconds and, for a directory, no
        process holds its lock (:meth:`scratch_dir`). Hidden directories are removed whole
        and not looked into.

        Parameters
        ----------
        older_than : float   age in seconds (newest modification time in the tree)
        now : float          the current time (``time.time()``; for tests)
        """
        now = time.time() if now is None else now
        removed: list[str] = []
        for dirpath, dirnames, filenames in os.walk(self.root):
            hidden = [d for d in dirnames if d.startswith(".")]
            dirnames[:] = [d for d in dirnames if not d.startswith(".")]
            for name in hidden + [f for f in filenames if f.startswith(".")]:
                path = Path(dirpath, name)
                try:
                    if now - _newest_mtime(path) < older_than or not _remove_unlocked(path):
                        continue
                except FileNotFoundError:  # its owner finished meanwhile
                    continue
                removed.append(path.relative_to(self.root).as_posix())
        return removed

    def health(self, min_free_bytes: int = 0) -> StoreHealth:
        """Probe whether the store can be written and has ``min_free_bytes`` free.

        Writes, fsyncs and removes a small hidden probe file in the root; never raises for
        a storage fault (the answer says what is wrong, without server paths).
        """
        probe = self.root / f".probe-{new_token()}.tmp"
        reason = ""
        writable = True
        try:
            fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, FILE_MODE)
            try:
                os.write(fd, b"facesynth readiness probe\n")
                os.fsync(fd)
            finally:
                os.close(fd)
                probe.unlink(missing_ok=True)
        except OSError as error:
            writable = False
            text = os.strerror(error.errno or errno.EIO)
            reason = (f"the blob store is full ({text})"
                      if error.errno in (errno.ENOSPC, errno.EDQUOT) else
                      f"the blob store is not writable ({text})")
        try:
            stat = os.statvfs(self.root)
            free, total = stat.f_bavail * stat.f_frsize, stat.f_blocks * stat.f_frsize
        except OSError as error:
            free = total = 0
            text = os.strerror(error.errno or errno.EIO)
            reason = reason or f"the blob store cannot be inspected ({text})"
        if not reason and free < min_free_bytes:
            reason = (f"the blob store is nearly full: {free} bytes free, fewer than the "
                      f"{min_free_bytes} required")
        return StoreHealth(writable, int(free), int(total), reason)

    # -- deleting ------------------------------------------------------------------------
    def delete(self, key: str) -> bool:
        """Remove the file or directory blob (or key prefix) ``key``.

        A directory is first renamed to a temporary name, so no reader sees it half gone.

        Returns
        -------
        bool   whether anything was there
        """
        path = self.path(key)
        if path.is_dir() and not path.is_symlink():
            doomed = self._temporary_sibling(path)
            try:
                os.rename(path, doomed)
            except FileNotFoundError:
                return False
            shutil.rmtree(doomed)
        else:
            try:
                path.unlink()
            except FileNotFoundError:
                return False
        _fsync_dir(path.parent)
        return True


# -- file-system helpers -----------------------------------------------------------------
def _newest_mtime(path: Path) -> float:
    """The latest modification time of ``path`` or of anything under it (seconds)."""
    newest = path.lstat().st_mtime
    if path.is_dir() and not path.is_symlink():
        for dirpath, dirnames, filenames in os.walk(path):
            for name in dirnames + filenames:
                try:
                    newest = max(newest, os.lstat(os.path.join(dirpath, name)).st_mtime)
                except FileNotFoundError:
                    pass
    return newest


def _remove_unlocked(path: Path) -> bool:
    """Remove a file, or a directory nobody holds a ``flock`` on; whether it was removed."""
    if not path.is_dir() or path.is_symlink():
        path.unlink()
        return True
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False                      # a live scratch directory
        shutil.rmtree(path, ignore_errors=True)
        return True
    finally:
        os.close(fd)


def _walk_files(top: Path) -> Iterator[tuple[Path, str]]:
    """Regular files under ``top`` as (path, relative POSIX path), sorted.

    Raises
    ------
    ValueError   for a symbolic link or anything that is neither a file nor a directory
    """
    for dirpath, dirnames, filenames in os.walk(top):
        dirnames.sort()
        for name in dirnames + filenames:
            path = Path(dirpath, name)
            if path.is_symlink() or not (path.is_file() or path.is_dir()):
                raise ValueError(f"{path} is a symbolic link or special file; a directory "
                                 "blob holds only regular files and directories")
        for name in sorted(filenames):
            path = Path(dirpath, name)
            yield path, path.relative_to(top).as_posix()


def _digest(source: BinaryIO) -> tuple[str, int]:
    """(sha256, size) of a stream, read in chunks."""
    h = hashlib.sha256()
    size = 0
    while block := source.read(CHUNK):
        h.update(block)
        size += len(block)
    return h.hexdigest(), size


def _copy(source: BinaryIO, target: BinaryIO) -> tuple[str, int]:
    """Copy a stream in chunks; flush and fsync ``target``; return (sha256, bytes copied)."""
    h = hashlib.sha256()
    size = 0
    while block := source.read(CHUNK):
        target.write(block)
        h.update(block)
        size += len(block)
    target.flush()
    os.fsync(target.fileno())
    return h.hexdigest(), size


def _create(path: Path) -> BinaryIO:
    """A new file opened for binary writing, mode 0644 whatever the umask."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, FILE_MODE)
    os.fchmod(fd, FILE_MODE)
    return os.fdopen(fd, "wb")


def _make_dir(path: Path) -> None:
    """Create one directory with mode 0755 whatever the umask (no error if it exists)."""
    try:
        os.mkdir(path, DIR_MODE)
    except FileExistsError:
        return
    os.chmod(path, DIR_MODE)
    _fsync_dir(path.parent)


def _fsync_dir(path: Path) -> None:
    """fsync a directory, making the renames and creations in it durable."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _check(key: str, expected: str, actual: str) -> None:
    if actual != expected:
        raise BlobCorrupt(key, expected, actual)
