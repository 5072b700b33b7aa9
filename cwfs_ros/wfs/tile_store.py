"""Field tiles kept on disk, so that a process starts with the tiles an earlier one built.

A field tile (:mod:`.mapping`) is a fit of ray traces over a patch of the field: ~1.2 s of
batoid per mapping tile, about 9 per LSST corner half-chip, and the design Zernikes' tiles
besides. A worker serving frames builds every tile of its half-chips at start, so without a
store each start of ``wavefront_node``, and each ``cwfs-ros replay`` of a frames bag, traces
for about a minute on a 2-core machine before its first visit. The tiles depend only on the
instrument, the band, the pupil grid and the code that fits them, so the store keeps them
under a digest of exactly that:

* the file name is the digest of the tile's own key (instrument, side, defocus, band,
  wavelength, tile, tile size, a digest of the pupil points) and of a *salt*, which names the
  fitting code (the source of :mod:`.mapping`), batoid's and numpy's versions and the
  store's format: a change to any of them reads nothing written before;
* a file holds plain arrays (``numpy.savez``, read with ``allow_pickle=False``): nothing in
  it is executed. Beside them it holds a digest of its own key and one of its arrays' names,
  dtypes, shapes and bytes, both checked on every read: a file copied or renamed over
  another tile's, or damaged, is rejected and rebuilt, never used for the wrong field;
* the tiles of other code or library versions are removed once unused for 30 days;
* a file is written whole under a temporary name and renamed, so that a reader, or another
  worker writing the same tile, never sees part of one; a file that cannot be read, or whose
  content the caller finds malformed, is rebuilt and replaced, never trusted;
* every rejected file and failed write is kept (:attr:`TileStore.problems`,
  :meth:`TileStore.report`): ``wavefront_node`` logs them and shows them on ``/diagnostics``.

A tile read from the store is the one the process would have built, to the last bit (the
same fit of the same traces; ``test_tile_store``). The store is off unless a caller turns it
on (:func:`use_tile_store`): ``wavefront_node``'s workers and ``cwfs-ros replay`` do, with the
``tile_store`` parameter (default ``$ROS_HOME/cwfs_ros/tiles``).
"""

from __future__ import annotations

import hashlib
import os
import re
import stat
import tempfile
from pathlib import Path

import numpy as np

from cwfs_ros.errors import TileStoreError

__all__ = ["TileStore", "use_tile_store", "active_tile_store"]

# Bump when the layout of a stored tile changes.
STORE_FORMAT = 2
# The tiles of other code or library versions are removed after this long unused.
PRUNE_AFTER_DAYS = 30.0
USED_MARK = ".last_used"
# The arrays a stored file holds besides the tile's: the digest of its key, and of the rest.
KEY_FIELD = "__tile_key__"
SUM_FIELD = "__tile_sum__"
# The salt directories' names (:attr:`TileStore.dir`): only these are ever pruned.
SALT_DIR_NAME = re.compile(r"[0-9a-f]{16}")
# A stored tile is ~1 MB; a file or its unpacked arrays above this is not one of ours.
MAX_TILE_BYTES = 256 * 2**20
# How many problems (rejected files, failed writes) a store keeps to report.
PROBLEMS_KEPT = 5


class TileStore:
    """A directory of field tiles, one ``.npz`` per tile, under ``<root>/<salt>/<kind>/``.

    Args:
        root: the directory (made on the first write).
        salt: names the code and libraries that build the tiles (see the module docstring).
    """

    def __init__(self, root: str | Path, salt: str) -> None:
        self.root = Path(root).expanduser()
        self.salt = str(salt)
        # One directory per salt: the tiles of other code or library versions sit beside it
        # and are removed once unused for PRUNE_AFTER_DAYS (:meth:`prune`).
        self.dir = self.root / hashlib.blake2b(repr((STORE_FORMAT, self.salt)).encode(),
                                               digest_size=8).hexdigest()
        self.writes = 0
        self.rejected = 0  # files read but not used (unreadable, damaged, another tile's)
        self.failed_writes = 0
        self.write_errors: list[str] = []  # the last few failed writes
        self.problems: list[str] = []  # the last few rejected files and failed writes
        self.unusable = ""  # why the root cannot hold a store at all, once said

    def path(self, kind: str, parts: tuple) -> Path:
        """The file of the tile ``parts`` (its key: strings, numbers, tuples of them)."""
        digest = hashlib.blake2b(repr((STORE_FORMAT, self.salt, kind, parts)).encode(),
                                 digest_size=20).hexdigest()
        return self.dir / kind / f"{digest}.npz"

    def key_digest(self, kind: str, parts: tuple) -> str:
        """The digest of the tile's key that its file holds (not its name's digest: a file
        renamed over another's keeps its own)."""
        return hashlib.blake2b(repr(("key", STORE_FORMAT, self.salt, kind, parts)).encode(),
                               digest_size=32).hexdigest()

    def reject(self, kind: str, parts: tuple, why: str) -> None:
        """Record that the stored file of a tile was not used, and why (the caller rebuilds
        it and stores it anew)."""
        self.rejected += 1
        self._problem(f"rejected {kind} tile {self.path(kind, parts).name}: {why}")

    def report(self) -> str:
        """The store's problems in one line, or "" when there were none."""
        if not self.problems:
            return ""
        recent = " | ".join(self.problems[-3:])
        return (f"{self.rejected} stored tiles rejected and rebuilt, {self.failed_writes}"
                f" failed writes in {self.root} (latest: {recent})")

    def _problem(self, text: str) -> None:
        self.problems = [*self.problems[-(PROBLEMS_KEPT - 1):], text]

    def prune(self, max_age_days: float | None = None) -> list[Path]:
        """Mark this store's directory used now and remove the directories of other salts
        unused for ``max_age_days`` (default :data:`PRUNE_AFTER_DAYS`): an upgrade leaves
        the old tiles behind, ~40 MB a set. Returns what was removed; errors are ignored (a
        store that cannot be cleaned still works).

        Only what this store writes is ever removed: a directory named as a salt directory
        (16 hex digits), holding a :data:`USED_MARK`, and nothing but kind directories of
        tile files (:func:`_salt_dir_files`). Anything else under the root is someone
        else's and is left alone, however old."""
        import time

        age_s = 86400.0 * (PRUNE_AFTER_DAYS if max_age_days is None else max_age_days)
        removed = []
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            (self.dir / USED_MARK).touch()
            others = [d for d in self.root.iterdir() if d != self.dir]
        except (NotADirectoryError, FileExistsError) as exc:  # the root, or above, a file
            self._unusable(exc)
            return removed
        except OSError:  # read-only, say: its tiles may still be read
            return removed
        for d in others:
            files = _salt_dir_files(d)
            if files is None:
                continue
            try:
                used = max(f.lstat().st_mtime for f in files)  # the mark, or a newer tile
                if time.time() - used > age_s:
                    _remove_salt_dir(d, files)
                    removed.append(d)
            except OSError:
                continue
        return removed

    def _unusable(self, exc: OSError) -> None:
        """Record, once, that the root cannot hold a store (it, or a directory above it, is
        a file): tiles are built every start, nothing else."""
        if not self.unusable:
            self.unusable = (f"cannot write or read tiles in {self.root}, every start builds"
                             f" them ({type(exc).__name__}: {exc})")
            self._problem(self.unusable)

    def load(self, kind: str, parts: tuple) -> dict[str, np.ndarray] | None:
        """The arrays stored for the tile, or None: not stored, or rejected (unreadable, its
        key or content digest wrong: recorded, :meth:`reject`)."""
        path = self.path(kind, parts)
        try:
            return _verified(_read_tile_file(path), self.key_digest(kind, parts))
        except FileNotFoundError:
            return None
        except NotADirectoryError as exc:  # the root, or a part of it, is a file: no store
            self._unusable(exc)
            return None
        except TileStoreError as exc:  # not a tile file, another tile's, or damaged
            self.reject(kind, parts, str(exc))
            return None
        except Exception as exc:  # noqa: BLE001 - truncated, not an npz (BadZipFile, ...):
            self.reject(kind, parts, f"unreadable ({type(exc).__name__}: {exc})")
            return None  # the caller builds the tile and stores it anew

    def save(self, kind: str, parts: tuple, arrays: dict[str, np.ndarray]) -> None:
        """Store the tile's arrays (whole or not at all). A store that cannot be written
        (read-only, full disk) costs the next process the build, nothing else: the error is
        kept in :attr:`write_errors` (the last few), not raised."""
        path = self.path(kind, parts)
        tmp = None
        marked = {**arrays, KEY_FIELD: np.array(self.key_digest(kind, parts)),
                  SUM_FIELD: np.array(_content_digest(arrays))}
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tile-", suffix=".npz")
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **marked)
            os.replace(tmp, path)
            tmp = None
            self.writes += 1
        except OSError as exc:
            self.failed_writes += 1
            self.write_errors = [*self.write_errors[-(PROBLEMS_KEPT - 1):], f"{path}: {exc}"]
            if isinstance(exc, NotADirectoryError):  # no store at all: said once
                self._unusable(exc)
            else:
                self._problem(f"cannot write {path}: {exc}")
        finally:
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)


def _read_tile_file(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a stored tile file. Only a regular file of sane size is read: a FIFO or
    device put in the store would block or never end a read, and is refused
    (:class:`TileStoreError`) without waiting; OS errors propagate."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO opens without a writer
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise TileStoreError(f"it is not a regular file ({stat.filemode(st.st_mode)})")
        if st.st_size > MAX_TILE_BYTES:
            raise TileStoreError(f"it is {st.st_size} bytes, more than a tile's"
                                 f" {MAX_TILE_BYTES}")
        with np.load(f, allow_pickle=False) as z:
            unpacked = sum(i.file_size for i in z.zip.infolist())
            if unpacked > MAX_TILE_BYTES:  # a small file that inflates without end
                raise TileStoreError(f"it unpacks to {unpacked} bytes, more than a tile's"
                                     f" {MAX_TILE_BYTES}")
            return {k: z[k] for k in z.files}


def _salt_dir_files(d: Path) -> list[Path] | None:
    """Every file of ``d`` if it is a salt directory this store wrote (named as one, holding
    its :data:`USED_MARK`, and only kind directories of tile files below it, none of them a
    symbolic link), else None."""
    if not SALT_DIR_NAME.fullmatch(d.name) or d.is_symlink() or not d.is_dir():
        return None
    try:
        files = [d / USED_MARK]
        if not stat.S_ISREG(files[0].lstat().st_mode):
            return None
        for kind in d.iterdir():
            if kind.name == USED_MARK:
                continue
            if kind.is_symlink() or not kind.is_dir():
                return None
            for f in kind.iterdir():
                if f.is_symlink() or not f.is_file() or f.suffix != ".npz":
                    return None
                files.append(f)
    except OSError:
        return None
    return files


def _remove_salt_dir(d: Path, files: list[Path]) -> None:
    """Remove a salt directory's files one by one, then its (now empty) directories, each
    through a descriptor of its directory opened without following links: a directory
    swapped for a link since :func:`_salt_dir_files` looked is not followed (the open
    fails), and a file that appeared meanwhile keeps its directory."""
    flags = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW
    top = os.open(d, flags)
    try:
        kinds: dict[str, int] = {}
        try:
            for f in files:
                rel = f.relative_to(d).parts
                if len(rel) == 1:
                    _unlink_regular(rel[0], top)
                else:
                    if rel[0] not in kinds:
                        kinds[rel[0]] = os.open(rel[0], flags, dir_fd=top)
                    _unlink_regular(rel[1], kinds[rel[0]])
        finally:
            for fd in kinds.values():
                os.close(fd)
        for name in kinds:
            os.rmdir(name, dir_fd=top)
    finally:
        os.close(top)
    d.rmdir()


def _unlink_regular(name: str, dir_fd: int) -> None:
    """Remove the regular file ``name`` of the directory ``dir_fd`` (anything else stays)."""
    try:
        st = os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
    except FileNotFoundError:
        return
    if stat.S_ISREG(st.st_mode):
        os.unlink(name, dir_fd=dir_fd)


def _content_digest(arrays: dict[str, np.ndarray]) -> str:
    """A digest of the arrays' names, dtypes, shapes and bytes."""
    h = hashlib.blake2b(digest_size=32)
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(repr((name, a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _verified(arrays: dict[str, np.ndarray], key_digest: str) -> dict[str, np.ndarray]:
    """The tile's arrays of a stored file, after checking its key and content digests;
    :class:`TileStoreError` when either is missing or wrong."""
    key, total = arrays.pop(KEY_FIELD, None), arrays.pop(SUM_FIELD, None)
    if key is None or total is None:
        raise TileStoreError("it holds no key or content digest (not written by this store)")
    if str(key) != key_digest:
        raise TileStoreError("it holds another tile (its key digest differs)")
    if str(total) != _content_digest(arrays):
        raise TileStoreError("its content is damaged (the content digest differs)")
    return arrays


_ACTIVE: TileStore | None = None


def use_tile_store(root: str | Path | None, salt: str = "") -> TileStore | None:
    """Keep this process's field tiles in ``root`` from now on (None or ``""``: off).
    Returns the store in use."""
    global _ACTIVE
    _ACTIVE = TileStore(root, salt) if root else None
    if _ACTIVE is not None:
        _ACTIVE.prune()
    return _ACTIVE


def active_tile_store() -> TileStore | None:
    """The store this process reads and writes its field tiles in, or None."""
    return _ACTIVE
