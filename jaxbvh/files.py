"""Writing files so that a failed write loses nothing: :func:`atomic_write`; keeping a
cache folder under a size: :func:`trim_least_recent`.

Every file the library and the ``jaxbvh`` tool write (trees, hits, images, batch
outputs, cached meshes) goes through :func:`atomic_write`: the bytes go to a temporary
file in the target's folder, which is renamed over the target only once it is complete.
A write that fails part-way (a full disk, a file size limit, an exception in the code
producing the bytes) leaves the old file byte-for-byte as it was and no temporary
behind. (A module of its own, below :mod:`jaxbvh.tree` and :mod:`jaxbvh.io`, because
both write files and :mod:`jaxbvh.io` imports :mod:`jaxbvh.tree`.)

The caches jaxbvh keeps beside JAX's compiled programs (parsed meshes,
:mod:`jaxbvh.io.meshes`; traced programs, :mod:`jaxbvh.program_store`) follow one rule,
:func:`trim_least_recent`: a reader touches an entry's modification time when it reads it,
and after each write the entries read or written longest ago go first until the folder's
entries are under the cache's size in bytes.
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import stat


def temporary_name(name: str, pid: int, tag: str) -> str:
    """The name of :func:`atomic_write`'s temporary file for a target called ``name``
    (``.<name>.<pid>.<tag>.tmp``; ``tag``: 8 hex digits)."""
    return f".{name}.{pid}.{tag}.tmp"


def remove_abandoned_temporaries(folder: str | os.PathLike, names) -> list[str]:
    """Remove the temporary files :func:`atomic_write` left in ``folder`` for targets
    called one of ``names`` when their writer died mid-write (killed: no ``except`` ran).
    Call it only once no process writes those targets any more (a batch run calls it for
    the outputs it has delivered). Only names of exactly :func:`temporary_name`'s form are
    touched; one pass over the folder. Returns the names removed."""
    temporary = re.compile(r"\.(.+)\.[0-9]+\.[0-9a-f]{8}\.tmp\Z")  # temporary_name's form
    names = set(names)
    removed = []
    with contextlib.suppress(FileNotFoundError), os.scandir(folder) as entries:
        for entry in entries:
            match = temporary.match(entry.name)
            if match and match.group(1) in names and entry.is_file(follow_symlinks=False):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(entry.path)
                    removed.append(entry.name)
    return removed


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb"):
    """A file object to write ``path``'s new contents to; ``path`` is replaced when the
    ``with`` block ends without an exception, and left as it was otherwise.

    The temporary file sits in ``path``'s folder (``.<name>.<pid>.<random>.tmp``), so the
    final :func:`os.replace` is a rename within one file system: readers see the old file
    or the new one, never a part. The contents are flushed to disk (``fsync``) before the
    rename, so errors the file system reports late (a full disk) still leave the old
    file. An existing target keeps its permission bits; a symbolic link keeps pointing
    where it did (the file it points to is replaced).

    Raises the block's exception after removing the temporary file; an ``OSError``
    (from the block or from the write itself) is raised again naming ``path``, as
    ``OSError(errno, strerror, path)``.
    """
    path = os.fspath(path)
    target = os.path.realpath(path)  # write through a link, as open(path, "w") would
    folder, name = os.path.split(target)
    tmp = os.path.join(folder, temporary_name(name, os.getpid(), secrets.token_hex(4)))
    try:
        # "x": never over another file; the umask applies, as for any new file
        with open(tmp, mode.replace("w", "x")) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        with contextlib.suppress(FileNotFoundError):
            os.chmod(tmp, stat.S_IMODE(os.stat(target).st_mode))
        os.replace(tmp, target)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.filename != path:
            raise OSError(exc.errno, exc.strerror or str(exc), path) from exc
        raise


def trim_least_recent(paths, max_bytes: int, keep=None) -> int:
    """Remove the files of ``paths`` (an iterable of paths: one cache's entries) used
    longest ago (oldest modification time first: readers touch what they read) until the
    rest take at most ``max_bytes`` bytes; ``keep`` (the entry just written) stays. A file
    removed meanwhile by another process is skipped, one that cannot be removed is left.
    Returns the bytes the remaining entries take."""
    entries = []
    for path in paths:
        try:
            st = os.stat(path)  # once: its time and size together
        except OSError:
            continue  # removed meanwhile by another process
        entries.append((st.st_mtime_ns, st.st_size, path))
    total = sum(size for _, size, _ in entries)
    for _, size, path in sorted(entries, key=lambda e: e[0]):
        if total <= max_bytes:
            break
        if keep is not None and os.fspath(path) == os.fspath(keep):
            continue
        with contextlib.suppress(OSError):
            os.unlink(path)
            total -= size
    return total
