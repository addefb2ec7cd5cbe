"""Reading a transient step's YAML block into its config dataclass, checked at the door.

Each step's settings live in one dataclass (defaults there only, in the units of the YAML
keys: a key ending in ``_arcmin``, ``_deg`` or ``_hz`` is in that unit, and the dataclass
offers the radians/Hz value as a property). Each field is a :func:`setting`: its default,
unit and meaning, which the documentation's tables read. :func:`from_yaml` converts a YAML
mapping into it once, when sotodlib builds the pipeline, and refuses a misspelt key or a value of the wrong
type with one line naming the step and the key, before any data are read.
"""
from __future__ import annotations

import dataclasses
import difflib


class ConfigError(ValueError):
    """A step's config has an unknown key or a value that cannot be used."""


def setting(default=dataclasses.MISSING, unit: str = "", doc: str = "", **field_kwargs):
    """A config dataclass field with its ``unit`` ('' when it has none) and its meaning
    ``doc`` in the field's metadata (``dataclasses.fields(cls)[i].metadata``), where the
    documentation's tables read them."""
    if not doc:
        raise ValueError("a setting needs its meaning (doc)")
    return dataclasses.field(default=default, metadata={"unit": unit, "doc": doc},
                             **field_kwargs)


def _convert(value, hint, where):
    """``value`` as the type named by the annotation ``hint`` (a string under PEP 563)."""
    hint = str(hint).replace(" ", "")
    optional = hint.endswith("|None") or hint.startswith("None|")
    base = hint.replace("|None", "").replace("None|", "")
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{where}: a value is required, got null")
    try:
        if base == "float":
            if isinstance(value, bool):
                raise TypeError
            return float(value)
        if base == "int":
            if isinstance(value, bool) or float(value) != int(value):
                raise TypeError
            return int(value)
        if base == "bool":
            if not isinstance(value, bool):
                raise TypeError
            return value
        if base == "str":
            if not isinstance(value, str):
                raise TypeError
            return value
        if base == "tuple":
            return tuple(float(v) for v in value)
        if base == "list":
            if isinstance(value, str):
                raise TypeError
            return list(value)
        if base == "dict":
            if not isinstance(value, dict):
                raise TypeError
            return dict(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected {base}{' or null' if optional else ''}, "
                          f"got {value!r}") from None
    return value


def from_yaml(cls, cfg, step):
    """An instance of the dataclass ``cls`` from the YAML mapping ``cfg`` of step ``step``."""
    return from_yaml_parts((cls,), cfg, step)[0]


def from_yaml_parts(classes, cfg, step) -> tuple:
    """One instance of each dataclass of ``classes`` from the YAML mapping ``cfg`` of step
    ``step``, whose keys are split between them by field name (one step's settings kept in
    several dataclasses, e.g. ``transient_find``'s paper-mode and coherent-mode keys)."""
    cfg = {} if cfg is None or isinstance(cfg, bool) else cfg   # `calc: true`, or no section
    if not isinstance(cfg, dict):
        raise ConfigError(f"{step}: the config block must be a mapping of keys, got {cfg!r}")
    owner = {f.name: (cls, f) for cls in classes for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(cfg) - set(owner))
    if unknown:
        hints = [f"{key} (did you mean {close[0]}?)" if close else key for key, close in
                 ((key, difflib.get_close_matches(str(key), owner, n=1)) for key in unknown)]
        raise ConfigError(f"{step}: unknown key(s) {', '.join(hints)}; expected some of "
                          f"{', '.join(sorted(owner))}")
    out = []
    for cls in classes:
        values = {k: _convert(v, owner[k][1].type, f"{step}: {k}")
                  for k, v in cfg.items() if owner[k][0] is cls}
        try:
            out.append(cls(**values))
        except ConfigError:
            raise                                   # names the step already
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{step}: {exc}") from None
    return tuple(out)


def positive(step, **values):
    """Raise a ConfigError naming ``step`` and the key unless every value is > 0."""
    for key, value in values.items():
        if value is not None and not value > 0:
            raise ConfigError(f"{step}: {key} must be positive, got {value}")


def non_negative(step, **values):
    """Raise a ConfigError naming ``step`` and the key unless every value (None allowed) is 0
    or more (NaN is not)."""
    for key, value in values.items():
        if value is not None and not value >= 0:
            raise ConfigError(f"{step}: {key} must be 0 or more, got {value}")


def share(step, **values):
    """Raise a ConfigError naming ``step`` and the key unless every value is in (0, 1]: a
    share or fraction above 1 would switch its test off without saying so."""
    for key, value in values.items():
        if value is not None and not 0 < value <= 1:
            raise ConfigError(f"{step}: {key} is a share and must be in (0, 1], got {value}")


@dataclasses.dataclass
class ChunkConfig:
    """The one key of ``transient_fourier_filter`` and ``transient_glitches`` that is not
    sotodlib's (all their other keys are those of ``fourier_filter`` and ``glitches``)."""

    chunk_dets: int = setting(
        32, "", "detectors filtered at a time (a chunk's FFT buffers: about 100 MB each for one "
        "hour at f090)")
