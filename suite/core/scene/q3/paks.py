"""The Quake III virtual file system: .pk3 archives (zip files) on a search path.

Search path. Directories come from ``SPLITBENCH_OA_PATH`` then ``SPLITBENCH_SCENE_PATH`` (each an
``os.pathsep``-separated list), then Debian's install location of the OpenArena data packages
(``/usr/share/games/openarena/baseoa``). A listed directory may be the folder holding the .pk3 files, a game
folder's parent (its ``baseoa/`` is used) or the root of a ``dpkg-deb -x`` extraction (its
``usr/share/games/openarena/baseoa`` is used).

Override order, as in ioquake3's ``FS_AddGameDirectory``: inside one directory the archives are sorted by
name (case-insensitively) and a later archive overrides an earlier one (``pak6-patch088.pk3`` replaces files
of ``pak1-maps.pk3``). Directories listed earlier in the search path override later ones, the way a user's
home game directory overrides the install directory. Paths inside archives are matched case-insensitively
with ``/`` separators. Only archives are searched; a loose .bsp is loaded by giving its path.
"""
from __future__ import annotations

import hashlib
import os
import zipfile
from dataclasses import dataclass

from suite.errors import UserError

ENV_VARS = ("SPLITBENCH_OA_PATH", "SPLITBENCH_SCENE_PATH")
# Where Debian's openarena-*-data / -maps / -textures packages install their archives.
DEBIAN_BASEOA = "/usr/share/games/openarena/baseoa"
DEFAULT_DIRS = (DEBIAN_BASEOA,)
DEBIAN_PACKAGES = ("openarena-081-maps", "openarena-088-data", "openarena-data", "openarena-081-textures")


def normalise(path: str) -> str:
    """The lookup key of a path inside the virtual file system: lower case, ``/`` separators, no leading ``/``."""
    return path.replace("\\", "/").lstrip("/").lower()


def _pak_dir(directory: str) -> str | None:
    """The folder with .pk3 files for a search-path entry (see the module docstring), or None."""
    directory = os.path.expanduser(directory)
    for candidate in (directory, os.path.join(directory, "baseoa"),
                      os.path.join(directory, DEBIAN_BASEOA.lstrip("/"))):
        try:
            if any(name.lower().endswith(".pk3") for name in os.listdir(candidate)):
                return candidate
        except OSError:
            continue
    return None


def search_dirs() -> list[str]:
    """The search-path entries in priority order (highest first), whether or not they exist."""
    dirs: list[str] = []
    for var in ENV_VARS:
        dirs += [d for d in os.environ.get(var, "").split(os.pathsep) if d.strip()]
    return dirs + [d for d in DEFAULT_DIRS if d not in dirs]


def missing_data_message() -> str:
    """One line naming the fix when no OpenArena archive is found."""
    return ("OpenArena maps not found: install the Debian packages " + ", ".join(DEBIAN_PACKAGES) +
            " (scripts/setup.sh does it when run as root), or without root `apt-get download` them, unpack each with "
            "`dpkg-deb -x PACKAGE.deb DIR` and set SPLITBENCH_OA_PATH=DIR (os.pathsep-separated; searched: "
            + os.pathsep.join(search_dirs()) + "); see docs/scenes.md")


@dataclass(frozen=True)
class Entry:
    pak: str  # archive path
    name: str  # the member name as stored in the archive
    size: int
    crc: int


class PakFS:
    """Case-insensitive view of the files in a list of archives, later archives overriding earlier ones.

    ``paks`` are archive paths from lowest to highest priority. ``read(path)`` returns a file's bytes from
    the archive that wins; ``find(path)`` returns its :class:`Entry` (or None).
    """

    def __init__(self, paks: list[str]):
        self.paks = list(paks)
        self._index: dict[str, Entry] = {}
        self._all: dict[str, list[Entry]] = {}
        self._zips: dict[str, zipfile.ZipFile] = {}
        for pak in self.paks:
            try:
                zf = zipfile.ZipFile(pak)
            except (OSError, zipfile.BadZipFile) as exc:
                raise UserError(f"cannot read archive '{pak}': {exc}") from None
            self._zips[pak] = zf
            for info in zf.infolist():
                if info.is_dir():
                    continue
                entry = Entry(pak, info.filename, info.file_size, info.CRC)
                key = normalise(info.filename)
                self._index[key] = entry
                self._all.setdefault(key, []).append(entry)

    @classmethod
    def from_search_path(cls, extra_paks: tuple[str, ...] = ()) -> "PakFS":
        """All archives on the search path; ``extra_paks`` are added with the highest priority."""
        return cls(search_path_paks() + list(extra_paks))

    def __bool__(self) -> bool:
        return bool(self.paks)

    def find(self, path: str) -> Entry | None:
        return self._index.get(normalise(path))

    def versions(self, path: str) -> list[Entry]:
        """Every archive's copy of ``path``, lowest priority first."""
        return list(self._all.get(normalise(path), []))

    def read(self, path: str, entry: Entry | None = None) -> bytes:
        entry = entry or self.find(path)
        if entry is None:
            raise UserError(f"'{path}' is not in any archive on the search path")
        try:
            return self._zips[entry.pak].read(entry.name)
        except Exception as exc:  # OSError, BadZipFile, zlib.error, CRC mismatch: a damaged archive
            raise UserError(f"cannot read '{entry.name}' from '{entry.pak}': {exc}") from None

    def list(self, prefix: str, suffix: str) -> list[str]:
        """Lower-case keys under ``prefix`` ending in ``suffix`` (one per file, whichever archive wins)."""
        prefix, suffix = normalise(prefix), suffix.lower()
        return sorted(k for k in self._index if k.startswith(prefix) and k.endswith(suffix))

    def maps(self) -> dict[str, Entry]:
        """Map name (lower case, without ``maps/`` and ``.bsp``) -> the winning archive entry."""
        return {k[len("maps/"):-len(".bsp")]: self._index[k] for k in self.list("maps/", ".bsp")
                if "/" not in k[len("maps/"):]}

    def fingerprint(self) -> str:
        """A content hash of the whole file system from the archives' central directories (names, sizes and
        CRC-32s of every member, in priority order), cheap to compute without decompressing anything."""
        h = hashlib.sha256()
        for pak in self.paks:
            h.update(os.path.basename(pak).lower().encode() + b"\0")
            for info in self._zips[pak].infolist():
                h.update(f"{info.filename}\0{info.file_size}\0{info.CRC}\n".encode())
        return h.hexdigest()


def _pak_sort_key(name: str) -> str:
    # ioquake3's paksort/FS_PathCmp: case-insensitive, '\\' and '/' treated alike.
    return name.lower().replace("\\", "/")


def search_path_paks() -> list[str]:
    """Archives on the search path, lowest priority first (the order :class:`PakFS` expects)."""
    paks: list[str] = []
    seen: set[str] = set()
    for directory in reversed(search_dirs()):  # lowest priority first
        found = _pak_dir(directory)
        if found is None:
            continue
        real = os.path.realpath(found)
        if real in seen:
            continue
        seen.add(real)
        names = sorted((n for n in os.listdir(found) if n.lower().endswith(".pk3")), key=_pak_sort_key)
        paks += [os.path.join(found, n) for n in names if os.path.isfile(os.path.join(found, n))]
    return paks
