"""Generated worlds kept on disk, so that each is generated once per machine instead of once per process.

A procedural world takes about 150 ms to generate (its starts are checked by driving the robot from
each), and the shipped recipe's two actors meet nearly all of its 200 training worlds in a ten-minute
`make run` (each its own hundred): 15 s of an actor's CPU, taken from the learner on a shared
machine, every run (bench system early in a run: 50.9 updates/s with the cache warm, 45.5 without).
The cache keeps each world as JSON in
``<cache>/worlds/<generator fingerprint>/procedural-<seed>.json``; ``<cache>`` is
``$COGEXPLORE_CACHE_DIR`` (``off``: no cache), else ``$XDG_CACHE_HOME/cogexplore``, else
``~/.cache/cogexplore``. The fingerprint hashes all of ``shared/`` (the generator reaches the sensor,
the depth gate and the config there) and the MuJoCo and numpy versions, so a changed generator never
reads an old world. A file that cannot be read, or whose content does not match its checksum, is
generated anew and replaced (one warning); a cache that cannot be written is said once and the worlds
are generated each time: the cache saves time and never stops a process. The checksum finds damage,
not intent: whoever may write the cache folder may change the worlds read from it, as whoever may
write the runs folder may change its checkpoints.
"""

from __future__ import annotations

import errno
import functools
import hashlib
import json
import logging
import os
import secrets
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from shared.files import atomic_write_text, read_regular_file

T = TypeVar("T")

log = logging.getLogger(__name__)

CACHE_DIR_ENV = "COGEXPLORE_CACHE_DIR"
"""The cache folder; ``off`` (or empty) turns the cache off."""
FORMAT = 1
MAX_FILE_BYTES = 4 * 2**20
"""A cached world is ~10 KB of MJCF text: anything this large is not one."""

_unwritable: set[Path] = set()  # cache folders already said to be unwritable (said once each)


def cache_root() -> Path | None:
    """The cache folder (see the module), None when the cache is off or no home folder is known."""
    value = os.environ.get(CACHE_DIR_ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "off") else Path(value)
    base = os.environ.get("XDG_CACHE_HOME", "")
    if os.path.isabs(base):  # the XDG spec: a relative one is to be ignored
        return Path(base) / "cogexplore"
    if not os.path.isabs(os.environ.get("HOME", "/")):  # HOME="" reads as "/": no home folder is known
        return None
    try:
        home = Path.home()
    except (RuntimeError, KeyError):  # no HOME and no passwd entry (a container's arbitrary uid)
        return None
    return home / ".cache" / "cogexplore"


def fingerprint_of(sources: list[Path], versions: str) -> str:
    """16 hex digits of the names and bytes of ``sources`` and of ``versions``."""
    digest = hashlib.sha256()
    for path in sources:
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    digest.update(f"{versions} format {FORMAT}".encode())
    return digest.hexdigest()[:16]


def generator_sources() -> list[Path]:
    """The files the fingerprint reads: every module of ``shared/``."""
    return sorted(Path(__file__).resolve().parent.parent.rglob("*.py"))


@functools.cache
def generator_fingerprint() -> str:
    """The fingerprint of the code and libraries that generate a world (see the module)."""
    import mujoco
    import numpy as np

    return fingerprint_of(generator_sources(), f"mujoco {mujoco.__version__} numpy {np.__version__}")


def cache_path(root: Path, name: str) -> Path:
    """Where world ``name`` (``procedural:<seed>``) is kept under ``root``."""
    return root / "worlds" / generator_fingerprint() / f"{name.replace(':', '-')}.json"


def _checksum(fields: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()


def _encode(fields: dict[str, Any]) -> str:
    return json.dumps({"format": FORMAT, "fingerprint": generator_fingerprint(), "sha256": _checksum(fields),
                       "world": fields})


def _decode(data: bytes, name: str) -> dict[str, Any]:
    """The world's fields in a cache file's bytes; ValueError naming what is wrong."""
    doc = json.loads(data)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ValueError(f"not a format {FORMAT} world cache file")
    fields = doc.get("world")
    if not isinstance(fields, dict) or doc.get("sha256") != _checksum(fields):
        raise ValueError("its content does not match its checksum")
    if fields.get("name") != name:
        raise ValueError(f"it does not hold world {name!r}")
    return fields


def cached_world(name: str, build: Callable[[], T], to_fields: Callable[[T], dict[str, Any]],
                 from_fields: Callable[[dict[str, Any]], T]) -> T:
    """World ``name`` from the cache, else ``build()`` and kept there (see the module). ``to_fields``
    gives a world's JSON fields (its ``name`` among them); ``from_fields`` the world again, or
    ValueError for fields that are not one (the world module's own types stay there)."""
    root = cache_root()
    if root is None:
        return build()
    path = cache_path(root, name)
    try:
        return from_fields(_decode(read_regular_file(path, MAX_FILE_BYTES), name))
    except (FileNotFoundError, NotADirectoryError):  # not kept yet; the cache a file: said once, on the write
        pass
    except (OSError, ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError: ValueErrors
        log.warning("world cache file %s cannot be used (%s): world %r is generated anew and the file replaced",
                    path, exc, name)
    world = build()
    if root not in _unwritable:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            # a name of this writer's own: the processes of other containers sharing the folder have the same ids
            atomic_write_text(path, _encode(to_fields(world)), tag=f"{os.getpid()}-{secrets.token_hex(4)}")
        except OSError as exc:
            if exc.errno == errno.ENOENT:  # the folder was removed meanwhile (a user clearing the cache)
                return world
            _unwritable.add(root)
            log.warning("the world cache %s cannot be written (%s): generated worlds are not kept (set %s to "
                        "another folder, or to 'off')", root, exc.strerror or exc, CACHE_DIR_ENV)
    return world
