"""Joining names that come from configs or data (scenario ids, network names, shard names) to a root folder.

``safe_join(root, relative)`` is the one place that turns such a name into a path under ``root``. It refuses,
with :class:`UnsafePathError` (a ``ValueError``) naming the root, the offending name and what it came from:

* an empty name, a NUL byte;
* an absolute path (``/etc/passwd``, ``C:\\x``, ``\\\\server\\share``);
* any ``..`` component (``a/../../b``), even one that would stay inside ``root`` after normalisation;
* a path that resolves outside ``root`` because a component (already on disk) is a symlink pointing out.

Use it where the *name* is not the user's explicit choice: the user's own ``--out`` / ``out_dir`` is the root
and is taken as given; names read from manifests, scenario metadata, network names, job labels are joined
with ``safe_join``.
"""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath, PureWindowsPath


class UnsafePathError(ValueError):
    """A config- or data-provided relative path would escape its root folder."""


def safe_join(root: str | os.PathLike, relative: str | os.PathLike, what: str = "path", check_symlinks: bool = True) -> Path:
    """``root / relative``, refusing names that are absolute, contain ``..`` or escape ``root`` via symlinks.

    :param root: the folder everything must stay in (need not exist yet).
    :param relative: a relative name (``shard-00000.npz``, ``states/net__seed00001/w00010.state.xml.gz``).
    :param what: what the name is, for the error message (``"manifest field 'shards[3].file'"``).
    :param check_symlinks: also refuse a path whose symlinks (already on disk) lead out of ``root``; pass
        ``False`` for reading, where a user may keep shards on another disk behind a symlink.
    :returns: the joined path (not resolved: symlinks *inside* root are kept as they are).
    :raises UnsafePathError: naming ``root``, ``relative`` and ``what``.
    """
    rel = os.fspath(relative)
    root_p = Path(root)
    where = f"{what} {rel!r} (under {root_p})"
    if not isinstance(rel, str) or rel.strip() == "":
        raise UnsafePathError(f"{where}: empty name; give a relative file name")
    if "\x00" in rel:
        raise UnsafePathError(f"{where}: contains a NUL byte")
    if PurePosixPath(rel).is_absolute() or PureWindowsPath(rel).is_absolute() or PureWindowsPath(rel).drive or rel.startswith("\\"):
        raise UnsafePathError(f"{where}: absolute paths are not allowed here; give a name relative to {root_p}")
    parts = PurePosixPath(rel.replace("\\", "/")).parts
    if ".." in parts:
        raise UnsafePathError(f"{where}: '..' components are not allowed; the file must stay inside {root_p}")
    out = root_p.joinpath(*parts)
    if not check_symlinks:
        return out
    # symlinks already on disk: the resolved target must stay under the resolved root
    root_r = root_p.resolve()
    out_r = out.resolve()
    if out_r != root_r and root_r not in out_r.parents:
        raise UnsafePathError(f"{where}: resolves to {out_r}, outside {root_r} (a symlink points out of the folder)")
    return out


def safe_name(name: str, what: str = "name") -> str:
    """A single path component derived from data (network name, scenario id): no separators, not ``.``/``..``.

    Returns ``name`` unchanged when it is safe; raises :class:`UnsafePathError` otherwise.
    """
    s = str(name)
    if s in ("", ".", "..") or "/" in s or "\\" in s or "\x00" in s:
        raise UnsafePathError(f"{what} {s!r}: not usable as a file name (no '/', '\\\\', NUL, '.' or '..')")
    return s
