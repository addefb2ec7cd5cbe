"""Sphinx extension: the transient steps' config keys and the candidate columns, from the code.

Directives
----------
``.. step-config:: transient_find``
    One table per config dataclass of the step (its process class's ``spec.configs``,
    :class:`so_transients.preprocess.step_fields.StepSpec`): every key (YAML name), its
    default, unit and meaning, from ``dataclasses.fields`` and each field's metadata
    (:func:`so_transients.common.step_config.setting`). Each row carries the HTML id
    ``config-<step>-<key>`` (underscores as hyphens), which :func:`missing_from_docs` looks for.
``.. candidate-columns::``
    Every candidate column of :data:`so_transients.common.candidates.SCHEMA` saved to the
    archive: name, step, unit, meaning; row ids ``column-<name>``.

Checking the built pages
------------------------
:func:`missing_from_docs` takes the folder of a built HTML tree and returns the
``(step, key)`` pairs missing from it: ``(step, None)`` when a registered ``transient_*``
step has no ``autoclass`` entry, and ``(step, key)`` for every key of its config dataclasses
or of its docstring's example block that has no row. :func:`missing_columns` does the same
for the candidate columns. The pytest file calls them after ``sphinx-build``.
"""
from __future__ import annotations

import dataclasses
import inspect
import re
import textwrap
from dataclasses import dataclass
from html.parser import HTMLParser
from pathlib import Path

from docutils import nodes
from docutils.parsers.rst import directives

from so_transients.preprocess.step_settings import step_configs

STEP_PREFIX = "transient_"

@dataclass(frozen=True)
class ConfigKey:
    """One YAML key of a step: its dataclass, default (as YAML shows it), unit and meaning."""

    step: str
    name: str
    owner: str
    default: str
    unit: str
    meaning: str


# ------------------------------------------------------------------------ from the code

def registered_steps() -> dict:
    """``{name: process class}`` of sotodlib's preprocess registry entries named
    ``transient_*``, in registration order (importing ``so_transients`` registers them)."""
    import so_transients  # noqa: F401
    from sotodlib.preprocess import Pipeline

    return {name: cls for name, cls in Pipeline.PIPELINE.items()
            if name.startswith(STEP_PREFIX)}


def config_classes(step) -> list:
    """The config dataclasses of ``step``, in the order their keys are documented: its
    process class's ``spec.configs``. A :class:`LookupError` names a step that declares
    none."""
    configs = step_configs()
    if step not in configs:
        raise LookupError(f"step {step!r} declares no config dataclasses: give its process "
                          f"class a spec = StepSpec(configs=...)")
    return list(configs[step])


def example_block(process_cls) -> dict:
    """``{key: comment}`` of the example config block in a process class's docstring (the
    literal block after a line ending in ``::`` that holds ``- name:``)."""
    doc = inspect.getdoc(process_cls) or ""
    match = re.search(r"::\n\n((?:[ \t]+.*\n?|\n)+)", doc)
    out = {}
    while match:
        block = textwrap.dedent(match.group(1))
        if "- name:" in block:
            key = None
            for line in block.splitlines():
                m = re.match(r"^(\s*)(\w+):\s*([^#]*?)\s*(?:#(.*))?$", line)
                if m and len(m.group(1)) >= 4:
                    key = m.group(2)
                    out[key] = (m.group(4) or "").strip()
                elif key and re.match(r"^\s*#", line):
                    out[key] = (out[key] + " " + line.strip()[1:].strip()).strip()
                elif m:
                    key = None
            return out
        match = re.search(r"::\n\n((?:[ \t]+.*\n?|\n)+)", doc[match.end():])
    return out


def _yaml(value):
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_yaml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_yaml(v)}" for k, v in value.items()) + "}"
    return str(value)


def _default(f):
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _fields(cls):
    """(field, its dataclass) of every YAML key of ``cls``, nested dataclasses flattened."""
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        default = _default(f)
        if dataclasses.is_dataclass(default) and not isinstance(default, type):
            yield from _fields(type(default))
        else:
            yield f, cls


def config_keys(step) -> list:
    """Every key of ``step``'s config dataclasses as :class:`ConfigKey`, in source order. A
    :class:`LookupError` names a field declared without :func:`~so_transients.common.
    step_config.setting` (no unit and meaning to show)."""
    out, seen = [], set()
    for cls in config_classes(step):
        for f, owner in _fields(cls):
            if f.name in seen:
                continue
            seen.add(f.name)
            where = f"{owner.__module__}.{owner.__qualname__}"
            if "doc" not in f.metadata:
                raise LookupError(f"{where}.{f.name} has no meaning: declare it with "
                                  f"so_transients.common.step_config.setting")
            default = _default(f)
            out.append(ConfigKey(step, f.name, where,
                                 "" if default is dataclasses.MISSING else _yaml(default),
                                 f.metadata["unit"], f.metadata["doc"]))
    return out


def documented_keys(step) -> list:
    """The keys the pages must show for ``step``: its dataclasses' and its docstring
    example's (a key only the example names is a key the table lacks)."""
    keys = [k.name for k in config_keys(step)]
    steps = registered_steps()
    if step in steps:
        keys += [k for k in example_block(steps[step]) if k not in keys]
    return keys


def row_id(step, key):
    return nodes.make_id(f"config-{step}-{key}")


def column_id(name):
    return nodes.make_id(f"column-{name}")


# ------------------------------------------------------------------------ directives

def _table(header, rows, widths, ids=None, title=None):
    table = nodes.table(classes=["colwidths-given"])
    if title:
        table += nodes.title(text=title)
    group = nodes.tgroup(cols=len(header))
    table += group
    for width in widths:
        group += nodes.colspec(colwidth=width)
    head = nodes.thead()
    group += head
    head += _row(header)
    body = nodes.tbody()
    group += body
    for k, cells in enumerate(rows):
        row = _row(cells)
        if ids:
            row["ids"].append(ids[k])
        body += row
    return table


def _row(cells):
    row = nodes.row()
    for cell in cells:
        entry = nodes.entry()
        para = nodes.paragraph()
        if isinstance(cell, nodes.Node):
            para += cell
        else:
            para += nodes.Text(str(cell))
        entry += para
        row += entry
    return row


def _literal(text):
    return nodes.literal(text=text) if text else nodes.Text("")


try:
    from sphinx.util.docutils import SphinxDirective
except ImportError:     # only the checking functions are used without Sphinx
    SphinxDirective = object


class StepConfig(SphinxDirective):
    """``.. step-config:: <step>``: the step's config keys, one table per dataclass."""

    required_arguments = 1
    has_content = False

    def run(self):
        step = self.arguments[0]
        if step not in registered_steps():
            raise self.error(f"step-config: {step!r} is not a registered step")
        try:
            keys = config_keys(step)
        except LookupError as err:
            raise self.error(f"step-config: {err}") from None
        container = nodes.container(classes=["step-config"])
        container["ids"].append(nodes.make_id(f"step-config-{step}"))
        for owner in dict.fromkeys(k.owner for k in keys):
            mine = [k for k in keys if k.owner == owner]
            rows = [(_literal(k.name), _literal(k.default), k.unit, k.meaning) for k in mine]
            container += _table(("key", "default", "unit", "meaning"), rows, (22, 16, 10, 52),
                                ids=[row_id(step, k.name) for k in mine],
                                title=f"{owner.rsplit('.', 1)[-1]} ({owner.rsplit('.', 1)[0]})")
        for source in (registered_steps()[step], *config_classes(step)):
            self.env.note_dependency(inspect.getsourcefile(source))
        return [container]


class CandidateColumns(SphinxDirective):
    """``.. candidate-columns::``: every saved candidate column of the schema."""

    has_content = False
    option_spec = {"step": directives.unchanged}

    def run(self):
        from so_transients.common import candidates

        cols = [c for c in candidates.columns(saved=True)
                if self.options.get("step") in (None, c.step)]
        rows = [(_literal(c.name), _literal(c.step), c.unit or "", c.description) for c in cols]
        self.env.note_dependency(inspect.getsourcefile(candidates))
        return [_table(("column", "step", "unit", "meaning"), rows, (18, 22, 10, 50),
                       ids=[column_id(c.name) for c in cols])]


# ------------------------------------------------------------------------ the docs check

class _Ids(HTMLParser):
    def __init__(self):
        super().__init__()
        self.ids = set()

    def handle_starttag(self, tag, attrs):
        for key, value in attrs:
            if key == "id" and value:
                self.ids.add(value)


def html_ids(html_dir) -> set:
    """Every ``id`` attribute in the ``.html`` files under ``html_dir``."""
    parser = _Ids()
    for path in sorted(Path(html_dir).rglob("*.html")):
        parser.feed(path.read_text(encoding="utf-8"))
    return parser.ids


def missing_from_docs(html_dir) -> list:
    """``(step, key)`` pairs the built HTML under ``html_dir`` lacks: ``(step, None)`` when a
    registered ``transient_*`` step has no ``autoclass`` entry (id: the process class's dotted
    path), ``(step, key)`` for each key of :func:`documented_keys` without a row of a
    ``step-config`` table. Empty when the pages are complete."""
    ids = html_ids(html_dir)
    missing = []
    for step, cls in registered_steps().items():
        if f"{cls.__module__}.{cls.__qualname__}" not in ids:
            missing.append((step, None))
        missing += [(step, key) for key in documented_keys(step) if row_id(step, key) not in ids]
    return missing


def missing_columns(html_dir) -> list:
    """Names of saved candidate columns without a row of a ``candidate-columns`` table."""
    from so_transients.common import candidates

    ids = html_ids(html_dir)
    return [c.name for c in candidates.columns(saved=True) if column_id(c.name) not in ids]


def setup(app):
    app.add_directive("step-config", StepConfig)
    app.add_directive("candidate-columns", CandidateColumns)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
