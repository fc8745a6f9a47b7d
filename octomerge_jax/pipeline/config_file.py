"""Settings files: ``MergeConfig`` as TOML (stdlib ``tomllib`` to read, a small writer here) or
JSON, with a comment per key from the sections' docstrings (``field_docs``).

    cfg = load_config("merge.toml")                      # partial files are fine
    text = dumps_toml(cfg)                               # what ``octomerge dump-config`` prints

Unknown keys and wrong types raise ``ValueError`` naming the file and the key, so a typo never
silently falls back to a default.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import textwrap
import tomllib
from pathlib import Path

from .._fileutil import atomic_write_bytes
from .config import MergeConfig, config_from_dict, config_to_dict

__all__ = ["dumps_toml", "field_docs", "load_config", "save_config"]


# ----------------------------------------------------------------------------- TOML / JSON


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")


def dumps_toml(cfg: MergeConfig, comments: bool = True) -> str:
    """The config as TOML text (one table per section). With ``comments``, each key is preceded
    by its description from the section's docstring, and optional settings left at ``None``
    (automatic) are written as comments so users see that they exist."""
    lines = ["# octomerge configuration (octomerge dump-config). Load with --config FILE;",
             "# command-line flags override these values. Omitted keys keep their defaults.", ""]
    for f in dataclasses.fields(cfg):
        section = getattr(cfg, f.name)
        docs = field_docs(type(section)) if comments else {}
        lines.append(f"[{f.name}]")
        for g in dataclasses.fields(section):
            v = getattr(section, g.name)
            if comments and g.name in docs:
                lines.extend(textwrap.wrap(docs[g.name], 96, initial_indent="# ", subsequent_indent="#   "))
            if v is None:
                if comments:
                    lines.append(f"# {g.name} = ...  (automatic)")
                continue
            lines.append(f"{g.name} = {_toml_value(list(v) if isinstance(v, tuple) else v)}")
        lines.append("")
    return "\n".join(lines)


_BULLET = re.compile(r"^\s*- ((?:``\w+``(?:\s*[/,]\s*)?)+)[^:]*:\s*(.*)$")


def field_docs(section_type) -> dict[str, str]:
    """``{key: description}`` from a config section's docstring bullets
    (``- ``key``: text`` or ``- ``a`` / ``b`` [unit]: text``), whitespace and RST quotes
    simplified."""
    out: dict[str, str] = {}
    fields = {f.name for f in dataclasses.fields(section_type)}
    names: list[str] = []
    text: list[str] = []

    def flush():
        doc = " ".join(" ".join(text).replace("``", "").split())
        for name in names:
            out.setdefault(name, doc)

    for line in (section_type.__doc__ or "").splitlines():
        m = _BULLET.match(line)
        if m:
            flush()
            names, text = re.findall(r"``(\w+)``", line.split(":", 1)[0]), [m.group(2)]
        elif names and line.strip():
            text.append(line.strip())
        elif names:
            flush()
            names, text = [], []
    flush()
    for name, doc in list(out.items()):  # keys described inside another key's text
        for other in re.findall(r"\b(\w+)\b", doc):
            if other != name and other in fields and other not in out:
                out[other] = doc
    return out


def load_config(path) -> MergeConfig:
    """Read a ``.toml`` or ``.json`` config file (UTF-8, partial files are fine). Raises
    ``FileNotFoundError``, ``IsADirectoryError`` or ``ValueError`` naming the file."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a directory, not a config file")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: config file not found")
    kind = "JSON" if path.suffix.lower() == ".json" else "TOML"
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not UTF-8 text (byte {err.start})") from None
    try:
        data = json.loads(text) if kind == "JSON" else tomllib.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not valid {kind}: {err}") from None
    except RecursionError:
        raise ValueError(f"{path}: not valid {kind}: nested too deeply") from None
    try:
        return config_from_dict(data)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None


def save_config(cfg: MergeConfig, path) -> None:
    """Write ``cfg`` as TOML (or JSON for a ``.json`` path), atomically."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        text = json.dumps(config_to_dict(cfg), indent=2) + "\n"
    else:
        text = dumps_toml(cfg)
    atomic_write_bytes(path, text.encode())
