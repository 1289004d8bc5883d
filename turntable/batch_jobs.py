"""The objects of a ``turntable batch`` and their settings: what each job reads, and its digest.

ROOT holds one folder (or video) per object (:func:`find_objects`); a manifest (``.csv``, ``.toml`` or
``.json``) lists them instead (:func:`read_manifest`). An object's own ``turntable.toml``/``turntable.json``
(:func:`read_settings`) and a manifest's row (:func:`check_settings`) override the command line's options,
paths relative to the object's (or the manifest's) folder. :func:`inputs_digest` is what ``--resume``
compares (the names, sizes and mtimes of the files read, and the options); :func:`memory_estimate` is
what a job asks Ray's scheduler for.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from .batch_report import RESERVED_NAMES
from .errors import UserError
from .frames import VIDEO_SUFFIXES
from .images import IMAGE_SUFFIXES, natural_key
from .stages.options import ReconstructOptions

__all__ = ["find_objects", "read_settings", "check_settings", "read_manifest", "ManifestEntry", "check_name",
           "object_input", "inputs_digest", "memory_estimate", "SETTINGS_FILES", "PATH_SETTINGS",
           "MANIFEST_SUFFIXES"]

SETTINGS_FILES = ("turntable.toml", "turntable.json")

#: Settings that name files: relative to the object's folder in its settings file
PATH_SETTINGS = ("input", "masks", "cameras", "intrinsics")


# --------------------------------------------------------------------------- objects and their settings


def find_objects(root: Path, out: Path | None = None) -> list[tuple[str, Path]]:
    """``(name, path)`` of every object in ROOT: its folders (not hidden, not OUT) and videos, natural order."""
    root = Path(root)
    if not root.is_dir():
        raise UserError(f"{root}: not a folder (ROOT holds one folder or video per object)")
    skip = out.resolve() if out is not None else None
    found = []
    for p in root.iterdir():
        if p.name.startswith(".") or (skip is not None and p.resolve() == skip):
            continue
        if p.is_dir():
            found.append((p.name, p))
        elif p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES:
            found.append((p.stem, p))
    names = [n for n, _ in found]
    for n, p in found:
        if n.casefold() in RESERVED_NAMES:
            check_name(n, str(p))  # not one of OUT's report files (other names: as the filesystem has them)
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise UserError(f"{root}: two objects would write OUT/{dup[0]} (a folder and a video of one name)")
    return sorted(found, key=lambda t: natural_key(t[0]))


def read_settings(path: Path, types: dict[str, tuple[type, ...]]) -> dict:
    """The object's own settings (``turntable.toml`` or ``turntable.json`` in its folder), keys with ``_``.

    ``types``: the settings allowed (``reconstruct``'s option names, ``-`` or ``_``) and their types; a
    ``no_X`` switch may also be given as ``X = false``. Paths (:data:`PATH_SETTINGS`) are made relative to
    the object's folder, other strings and numbers are returned as given. Raises ``UserError`` naming the
    file for a file that does not parse, an unknown key or a wrong type.
    """
    if not path.is_dir():
        return {}
    for fname in SETTINGS_FILES:
        f = path / fname
        if not f.is_file():
            continue
        raw = _load_table_file(f, "settings")
        if not isinstance(raw, dict):
            raise UserError(f"{f}: expected a table of settings")
        return check_settings(raw, types, base=path, where=str(f))
    return {}


def _load_table_file(f: Path, what: str):
    try:
        if f.suffix.lower() == ".toml":
            import tomllib

            return tomllib.loads(f.read_text())
        return json.loads(f.read_text())
    except (ValueError, OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{f}: cannot read the {what}: {exc}") from None


def check_settings(raw: dict, types: dict[str, tuple[type, ...]], *, base: Path, where: str,
                   text: bool = False) -> dict:
    """``raw`` settings checked against ``types`` (see :func:`read_settings`), keys with ``_``, paths made
    relative to ``base``. ``text``: the values are strings to convert (a CSV's cells; empty: not set).
    ``where`` starts every error message (a file, a manifest's row)."""
    settings = {}
    for key, value in raw.items():
        k = str(key).strip().replace("-", "_")
        if text:
            value = value.strip() if isinstance(value, str) else value
            if value in ("", None):
                continue
        if k not in types and types.get(f"no_{k}") == (bool,):  # fusion = false -> no_fusion = true
            if text:
                value = _from_text(value, (bool,), where, key)
            k, value = f"no_{k}", (not value) if isinstance(value, bool) else value
        if k not in types:
            raise UserError(f"{where}: unknown setting {key!r} (known: {', '.join(sorted(types))})")
        ok = types[k]
        if text:
            value = _from_text(value, ok, where, key)
        if not isinstance(value, ok) or (isinstance(value, bool) and bool not in ok):
            raise UserError(f"{where}: {key} = {value!r}: expected {' or '.join(t.__name__ for t in ok)}")
        if k in PATH_SETTINGS and not Path(value).is_absolute():
            value = str(base / value)
        settings[k] = str(value) if str in ok else value
    return settings


_TRUE, _FALSE = ("true", "yes", "1", "on"), ("false", "no", "0", "off")


def _from_text(value, ok: tuple[type, ...], where: str, key) -> object:
    """A CSV cell as the type a setting takes (a bool, an int, a float, or the text itself)."""
    if not isinstance(value, str) or str in ok:
        return value
    if bool in ok:
        if value.lower() in _TRUE + _FALSE:
            return value.lower() in _TRUE
        raise UserError(f"{where}: {key} = {value!r}: expected true or false")
    for t in (int, float):
        if t in ok:
            try:
                return t(value)
            except ValueError:
                pass
    raise UserError(f"{where}: {key} = {value!r}: expected {' or '.join(t.__name__ for t in ok)}")


# --------------------------------------------------------------------------- a manifest: the jobs listed in a file

MANIFEST_SUFFIXES = (".csv", ".toml", ".json")


@dataclass(frozen=True)
class ManifestEntry:
    """One job of a manifest: the object's name (``OUT/<name>``), its folder or video, its own settings
    (checked, keys with ``_``, paths absolute), and where it is written (for messages)."""

    name: str
    path: Path
    settings: dict
    where: str


def check_name(name: str, where: str) -> None:
    """``UserError`` unless ``name`` can be a folder of OUT of its own (one path component, not hidden, not
    one of OUT's report files)."""
    if not name or name != name.strip() or any(c in name for c in "/\\\0") or name.startswith("."):
        raise UserError(f"{where}: name {name!r}: must be a folder name (no '/', not empty, not starting with '.')")
    if name.casefold() in RESERVED_NAMES:
        raise UserError(f"{where}: name {name!r}: OUT/{name} is the batch's own (report files: "
                        f"{', '.join(RESERVED_NAMES)})")


def read_manifest(manifest: Path, types: dict[str, tuple[type, ...]]) -> list[ManifestEntry]:
    """The jobs a manifest lists (``.csv``, ``.toml`` or ``.json``); ``UserError`` naming the file, the row
    and the reason for the first bad row.

    - CSV: a header row (``name``, ``input``, then any settings, named as the options are), one row per
      object; an empty cell leaves the command line's value; booleans ``true``/``false``; a row whose
      first cell starts with ``#`` is a comment.
    - TOML: one ``[[jobs]]`` table per object; JSON: ``{"jobs": [{...}, ...]}`` (or the list alone).

    ``input`` (the object's folder or video) and every path setting are relative to the manifest's folder;
    ``name`` (``OUT/<name>``) defaults to the input's name (a video's without its suffix). Names must
    differ (also in case: OUT may be on a case-insensitive filesystem).
    """
    manifest = Path(manifest)
    if not manifest.is_file():
        raise UserError(f"--manifest {manifest}: file not found")
    suffix = manifest.suffix.lower()
    if suffix not in MANIFEST_SUFFIXES:
        raise UserError(f"--manifest {manifest}: expected a .csv, .toml or .json file")
    base = manifest.parent
    rows: list[tuple[str, dict]] = []
    if suffix == ".csv":
        try:
            text = manifest.read_text(encoding="utf-8-sig")
        except (OSError, UnicodeDecodeError) as exc:
            raise UserError(f"{manifest}: cannot read the manifest: {exc}") from None
        lines = [(i, ln) for i, ln in enumerate(text.splitlines(), 1) if ln.strip() and not ln.lstrip().startswith("#")]
        if not lines:
            raise UserError(f"{manifest}: empty (expected a header row: name,input,...)")
        try:
            table = list(csv.reader([ln for _, ln in lines], strict=True))
        except csv.Error as exc:
            raise UserError(f"{manifest}: not a CSV table: {exc}") from None
        header = [h.strip() for h in table[0]]
        if "input" not in header:
            raise UserError(f"{manifest}: line {lines[0][0]}: the header has no 'input' column (got {header})")
        dup = sorted({h for h in header if header.count(h) > 1})
        if dup or "" in header:
            raise UserError(f"{manifest}: line {lines[0][0]}: " + (f"column {dup[0]!r} twice" if dup else
                                                                  "a column without a name"))
        for (lineno, _), cells in zip(lines[1:], table[1:], strict=True):
            if len(cells) != len(header):
                raise UserError(f"{manifest}: line {lineno}: {len(cells)} cells, the header has {len(header)}")
            rows.append((f"line {lineno}", dict(zip(header, cells, strict=True))))
    else:
        raw = _load_table_file(manifest, "manifest")
        entries = raw.get("jobs") if isinstance(raw, dict) and set(raw) == {"jobs"} else raw
        if not isinstance(entries, list) or not entries:
            what = "[[jobs]] tables" if suffix == ".toml" else '{"jobs": [...]} or a list'
            raise UserError(f"{manifest}: expected {what}, one per object")
        for i, e in enumerate(entries, 1):
            if not isinstance(e, dict):
                raise UserError(f"{manifest}: job {i}: expected a table of settings, got {e!r}")
            rows.append((f"job {i}", e))
    jobs: list[ManifestEntry] = []
    seen: dict[str, str] = {}
    for row, entry in rows:
        where = f"{manifest}: {row}"
        entry = dict(entry)
        text = suffix == ".csv"
        name = entry.pop("name", None)
        inp = entry.pop("input", None)
        if inp is None or (isinstance(inp, str) and not inp.strip()):
            raise UserError(f"{where}: no input (the object's folder or video, relative to the manifest's folder)")
        if not isinstance(inp, str):
            raise UserError(f"{where}: input = {inp!r}: expected a path (a string)")
        path = base / inp.strip()
        if not (path.is_dir() or (path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES)):
            raise UserError(f"{where}: input {inp!r}: " + (f"not a folder or a video ({', '.join(VIDEO_SUFFIXES)})"
                                                          if path.exists() else f"{path}: not found"))
        if name is None or (isinstance(name, str) and not name.strip()):
            name = path.name if path.is_dir() else path.stem
        if not isinstance(name, str):
            raise UserError(f"{where}: name = {name!r}: expected a string")
        name = name.strip() if text else name
        check_name(name, where)
        where = f"{where} ({name})"
        if name.casefold() in seen:
            raise UserError(f"{where}: name {name!r} already used by {seen[name.casefold()]}: two jobs would "
                            f"write OUT/{name}")
        seen[name.casefold()] = row
        settings = check_settings(entry, {k: v for k, v in types.items() if k != "input"}, base=base,
                                  where=where, text=text)
        jobs.append(ManifestEntry(name=name, path=path, settings=settings, where=where))
    return jobs


# --------------------------------------------------------------------------- what a job reads, what it needs


def object_input(path: Path) -> Path:
    """What ``reconstruct`` reads for an object: a video as it is; a folder's ``images/`` if it has one
    (the layout ``turntable synth`` writes), else the folder itself."""
    return path / "images" if path.is_dir() and (path / "images").is_dir() else path


def _stat_rows(p: Path | None) -> list:
    if p is None:
        return []
    try:
        if p.is_dir():
            return [[q.name, q.stat().st_size, q.stat().st_mtime_ns] for q in sorted(p.iterdir()) if q.is_file()]
        st = p.stat()
        return [[str(p.resolve()), st.st_size, st.st_mtime_ns]]
    except OSError:
        return [[str(p), None, None]]


def inputs_digest(opts: ReconstructOptions) -> str:
    """What a finished output depends on: the turntable version, the options (not OUT, ``overwrite``,
    ``spawn``) and the names, sizes and mtimes of the files read (frames, masks, cameras, intrinsics)."""
    from . import __version__

    d = dataclasses.asdict(opts)
    for k in ("out", "overwrite", "spawn"):
        d.pop(k)
    files = {k: _stat_rows(v) for k, v in (("input", opts.input), ("masks", opts.masks_dir),
                                            ("cameras", opts.cameras), ("intrinsics", opts.intrinsics))}
    text = json.dumps({"version": __version__, "options": d, "files": files}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


#: Memory of a reconstruct process before its data (Python, numpy, OpenCV, open3d, Rerun), bytes
BASE_MEMORY = 600 << 20


def memory_estimate(opts: ReconstructOptions) -> int:
    """A rough peak (bytes) of one ``reconstruct``, for Ray's scheduler: the process, the work images and
    their silhouettes/distance maps (~24 bytes a pixel), the carving grid (~12 bytes a voxel) and, with
    fusion, the depth maps. Read from the first photo's header only."""
    n, full = 36, 1_300_000
    p = Path(opts.input)
    if p.is_dir():
        files = [q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES]
        n = len(files) // max(opts.every, 1) if opts.frames is None else min(opts.frames, len(files))
        if files:
            try:
                from PIL import Image

                with Image.open(min(files)) as im:
                    full = im.width * im.height
            except Exception:  # noqa: BLE001  (an estimate; the job itself says what is wrong with the photo)
                pass
    # the work images: at most ~1.3 MP by default, the photos with work_size 0 ('full'), else N x 3N/4
    px = min(full, 1_300_000) if opts.work_size is None else full if opts.work_size == 0 else \
        min(full, opts.work_size ** 2 * 3 // 4)
    per_px = 24 + (16 if opts.fusion else 0)
    return int(BASE_MEMORY + n * px * per_px + 12 * opts.resolution ** 3)

