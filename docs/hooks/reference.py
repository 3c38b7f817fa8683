"""MkDocs hook: the reference pages, generated from the code at every build.

- ``reference/cli.md``: every sub-command, argument and flag of ``oga``, walked from the
  argparse parsers (:func:`oga.cli.build_parser`);
- ``reference/rest.md``: every route of the service, its parameters, bodies and answers, from
  the OpenAPI schema of :func:`api.app.create_app`, and the routes outside the schema;
- ``reference/machine-file.md``: every field of a machine file, walked from the pydantic
  model :class:`oga.model.machine.Machine` (type, default, accepted range), and
  ``MACHINE_FIELD_RANGES``;
- ``reference/python.md``: the library, one mkdocstrings block per name of ``oga``'s public
  API (``oga._EXPORTS``) and per module of :data:`MODULES`;
- ``changelog.md``: ``CHANGELOG.md`` of the repository, as it is.

Nothing here is copied from the code: a flag, route or field added to the code appears in the
next build. ``python docs/hooks/reference.py DIR`` writes the pages to DIR (to read them
without building the site).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import textwrap
import types
import typing
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # `mkdocs build` from the checkout, installed or not
    sys.path.insert(0, str(ROOT))

#: Modules of the library documented whole (beside the names of ``oga._EXPORTS``).
MODULES = ("feedplan", "feedplan.plan", "oga.export.table", "oga.identify", "oga.search.robust.plants",
           "oga.verify.certificate", "oga.search.robust.search", "oga.report.optimize", "oga.defaults")

#: One line per machine-file field whose name alone does not say it (unit in the name
#: otherwise). A field missing here still appears; a key here that names no field fails the
#: docs test (``tests/test_docs.py``).
FIELD_NOTES = {
    "name": "name of the machine (written into every table and summary)",
    "source": "where the numbers come from (free text)",
    "axes": "one table per axis, named x, y or z",
    "axes.<a>.limits.vmax_m_s": "velocity limit of the axis (paper eq. 2)",
    "axes.<a>.limits.amax_m_s2": "acceleration limit",
    "axes.<a>.limits.jmax_m_s3": "jerk limit",
    "axes.<a>.limits.ferror_max_m": "following error the controller tolerates, checked at "
                                    "every sample (LinuxCNC: the least of FERROR, MIN_FERROR); "
                                    "unset: reported, not bounded",
    "axes.<a>.cascade.mass_kg": "moving mass",
    "axes.<a>.cascade.coulomb_n": "Coulomb friction Fc",
    "axes.<a>.cascade.static_n": "static friction, the Stribeck peak Fs (>= coulomb_n)",
    "axes.<a>.cascade.stribeck_m_s": "Stribeck velocity vs",
    "axes.<a>.cascade.viscous_n_s_m": "viscous friction B",
    "axes.<a>.cascade.kv_n_s_m": "velocity-loop proportional gain Kv",
    "axes.<a>.cascade.tn_s": "velocity-loop integral time Tn",
    "axes.<a>.cascade.force_lag_s": "force (current) loop, first-order lag tau",
    "axes.<a>.cascade.force_limit_n": "force the drive delivers at most",
    "axes.<a>.cascade.friction_smoothing_m_s": "velocity of the tanh that smooths the "
                                               "friction's sign",
    "axes.<a>.arx.num": "numerator of the velocity loop, coefficients of z^0, z^-1, ... "
                        "(leading zeros: the loop's delay)",
    "axes.<a>.arx.den": "denominator, den[0] = 1, stable",
    "axes.<a>.arx.coulomb_m_s": "Coulomb friction as an input-equivalent velocity",
    "axes.<a>.arx.viscous_ratio": "viscous friction as a share of the velocity",
    "axes.<a>.arx.friction_smoothing_m_s": "velocity of the tanh that smooths the "
                                           "friction's sign",
    "axes.<a>.arx.load_m_s_per_n": "an external force as an input-equivalent velocity",
    "axes.<a>.uncertainty": "the set the robust search and its certificate cover: per "
                            "cascade field a (low, high) factor, low <= 1 <= high",
    "axes.<a>.uncertainty.dead_time_extra_samples": "whole samples added to the dead time",
    "timing.te_s": "position-loop period Te",
    "timing.substeps": "inner-loop (velocity PI, force loop) steps per Te",
    "timing.dead_time_samples": "dead time of the position loop's command, samples",
    "timing.friction_linear_below_m_s": "a simulation setting: below this speed over a "
                                        "whole period the friction is taken as its tangent "
                                        "at rest (unset: exact sub-steps)",
    "gains.kp_span_m_min_per_mm": "Kp range the stability margins are computed over",
    "gains.kp_bounds_m_min_per_mm": "configured Kp bounds (the stable range is cut to them)",
    "gains.kp_step_m_min_per_mm": "Kp grid step of the best fixed gains",
    "gains.kf_range": "Kf range",
    "gains.kf_step": "Kf grid step",
    "gains.pm_min_deg": "least phase margin of a stable Kp",
    "gains.gm_min_db": "least gain margin of a stable Kp",
    "planner.accel_fraction": "share of the acceleration limit the interpolator plans with "
                              "(the rest is the position loop's reserve)",
    "planner.jerk_fraction": "share of the jerk limit the interpolator plans with",
}


def _cell(text) -> str:
    """Text for a Markdown table cell."""
    return str(text).replace("|", "\\|").replace("\n", " ")


def _code(text) -> str:
    """A code span for a table cell (Markdown tables leave pipes inside backticks alone)."""
    return f"`{text}`"


def _numpydoc_summary(doc: str) -> str:
    """A docstring up to its first numpydoc section (``Attributes``, ``Parameters``, ...):
    the sections are the tables of these pages."""
    return re.split(r"\n[ \t]*\w[\w ]*\n[ \t]*-{3,}[ \t]*\n", "\n" + doc, maxsplit=1)[0].strip()


def _prose(doc: str) -> str:
    """A docstring as Markdown: its paragraphs, a ``::`` block as a code block, reST roles
    and double backquotes made plain."""
    out, literal = [], False
    for para in re.split(r"\n\s*\n", textwrap.dedent(doc).strip("\n")):
        if literal:
            out.append("```text\n" + textwrap.dedent(para) + "\n```")
            literal = False
            continue
        text = " ".join(para.split()).replace("``", "`")
        text = re.sub(r":(?:class|func|meth|data|mod|attr):`~?([^`]+)`", r"`\1`", text)
        if text.endswith("::"):
            text, literal = text[:-1], True
        out.append(text)
    return "\n\n".join(out)


# --- CLI ----------------------------------------------------------------------------------------

def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))


def cli_markdown() -> str:
    """The CLI reference: per sub-command its usage, description and every argument."""
    from oga.cli import build_parser

    parser = build_parser()
    sub = _subparsers(parser)
    helps = {c.dest: c.help for c in sub._choices_actions}
    lines = ["# Command line", "",
             "Generated at build time from the argparse parsers of `oga/cli/` "
             "(`oga COMMAND --help` prints the same). Common to every command: bad input "
             "ends with exit code 2 and one line naming what is wrong and where "
             "([Bad input](../howto/bad-input.md)).", "",
             "| command | what it does |", "|---|---|"]
    lines += [f"| [`oga {n}`](#oga-{n}) | {_cell(helps.get(n, ''))} |" for n in sub.choices]
    lines += ["", "`oga --version` prints the version.", ""]
    for name, sp in sub.choices.items():
        sp.formatter_class = lambda prog: argparse.HelpFormatter(prog, width=80)
        formatter = sp._get_formatter()
        what = helps.get(name, "")
        lines += [f"## oga {name}", "", what[:1].upper() + what[1:] + ".", ""]
        if sp.description:
            lines += [sp.description, ""]
        lines += ["```text", sp.format_usage().strip(), "```", "",
                  "| argument | value | default | meaning |", "|---|---|---|---|"]
        for a in sp._actions:
            names = ", ".join(_code(s) for s in a.option_strings) or _code(a.metavar or a.dest)
            if a.choices is not None:
                value = "one of " + ", ".join(_code(c) for c in a.choices)
            elif a.option_strings and a.nargs != 0:
                value = _code(a.metavar or a.dest.upper())
            elif not a.option_strings:
                value = {None: "required", "?": "optional", "+": "one or more",
                         "*": "any number"}.get(a.nargs, str(a.nargs))
            else:
                value = "switch"
            default = ("" if a.default in (None, False, argparse.SUPPRESS) or a.required
                       else _code(a.default))
            text = formatter._expand_help(a) if a.help else ""
            lines.append(f"| {names} | {value} | {default} | {_cell(text)} |")
        lines.append("")
    return "\n".join(lines)


# --- REST ---------------------------------------------------------------------------------------

def openapi_schema() -> tuple[dict, list]:
    """The service's OpenAPI schema and its routes (an app made, never started)."""
    from api.app import Settings, create_app

    with tempfile.TemporaryDirectory() as tmp:
        app = create_app(Settings(db_path=str(Path(tmp) / "jobs.db"), workers=0))
        return app.openapi(), list(app.routes)


def _type(schema: dict, defs: dict) -> str:
    """A short type of a JSON schema: ``string``, ``integer [1, 1000]``, ``JobOut``..."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[1]
        return f"[{name}](#{name.lower()})" if name in defs else name
    if "anyOf" in schema:
        return " or ".join(_type(s, defs) for s in schema["anyOf"])
    if "const" in schema:
        return json.dumps(schema["const"])
    if "enum" in schema:
        return " \\| ".join(json.dumps(v) for v in schema["enum"])
    kind = schema.get("type", "any")
    if kind == "array":
        if "prefixItems" in schema:
            return "[" + ", ".join(_type(s, defs) for s in schema["prefixItems"]) + "]"
        return f"array of {_type(schema.get('items', {}), defs)}"
    if kind == "object" and isinstance(schema.get("additionalProperties"), dict):
        return f"object of {_type(schema['additionalProperties'], defs)}"
    bounds = [f"{k} {schema[key]}" for key, k in (("minimum", ">="), ("exclusiveMinimum", ">"),
                                                  ("maximum", "<="), ("exclusiveMaximum", "<"),
                                                  ("minLength", "length >="),
                                                  ("maxLength", "length <="))
              if key in schema]
    return kind + (f" ({', '.join(bounds)})" if bounds else "")


def rest_markdown() -> str:
    """The REST reference: every operation of the OpenAPI schema, then its schemas."""
    spec, routes = openapi_schema()
    defs = spec.get("components", {}).get("schemas", {})
    info = spec["info"]
    lines = ["# REST API", "",
             f"Generated at build time from the OpenAPI schema of `api/app.py` "
             f"({info['title']} {info['version']}; a running server serves the same schema "
             "at `/openapi.json` and its interactive form at `/docs`). "
             "[The service](../tutorials/service.md) shows it at work.", "",
             info.get("summary", ""), "", info.get("description", "").strip(), "",
             "| method | path | what it does |", "|---|---|---|"]
    ops = [(m.upper(), p, op) for p, item in spec["paths"].items() for m, op in item.items()]
    anchor = {}
    for m, p, op in ops:
        anchor[m, p] = (m + "-" + p).lower().replace("/", "").replace("{", "").replace("}", "")
        lines.append(f"| {m} | [`{p}`](#{anchor[m, p]}) | {_cell(op.get('summary', ''))} |")
    outside = [r for r in routes if not getattr(r, "include_in_schema", True)
               and getattr(r, "path", "") not in ("/openapi.json", "/docs", "/redoc",
                                                  "/docs/oauth2-redirect")]
    outside += [r for r in routes if type(r).__name__ == "Mount"]
    if outside:
        lines += ["", "Outside the schema: " + ", ".join(
            f"`{' '.join(sorted(getattr(r, 'methods', None) or {'GET'}))} {r.path}`"
            f"{' (and below)' if type(r).__name__ == 'Mount' else ''}" for r in outside)
            + ": the web page and its files (no API key needed).", ""]
    for m, p, op in ops:
        lines += ["", f"## {m} {p} {{#{anchor[m, p]}}}", "", f"**{op.get('summary', '')}**", ""]
        if op.get("description"):
            lines += [_prose(_numpydoc_summary(op["description"])), ""]
        params = op.get("parameters", [])
        if params:
            lines += ["| parameter | in | type | required | default | meaning |",
                      "|---|---|---|---|---|---|"]
            for q in params:
                s = q.get("schema", {})
                default = _code(json.dumps(s["default"])) if "default" in s else ""
                lines.append(f"| `{q['name']}` | {q['in']} | {_type(s, defs)} | "
                             f"{'yes' if q.get('required') else 'no'} | {default} | "
                             f"{_cell(q.get('description', ''))} |")
            lines.append("")
        body = op.get("requestBody")
        if body:
            for media, content in body.get("content", {}).items():
                lines += [f"Body ({media}): {_type(content.get('schema', {}), defs)}.", ""]
        lines += ["| answer | meaning | body |", "|---|---|---|"]
        for code, resp in op.get("responses", {}).items():
            kinds = []
            for media, content in resp.get("content", {}).items():
                kinds.append(_cell(media) + (f": {_type(content['schema'], defs)}"
                                             if content.get("schema") else ""))
            lines.append(f"| {code} | {_cell(resp.get('description', ''))} | "
                         f"{'; '.join(kinds)} |")
    lines += ["", "## Schemas", ""]
    for name, schema in defs.items():
        lines += [f"### {name} {{#{name.lower()}}}", ""]
        if schema.get("description"):
            lines += [_prose(_numpydoc_summary(schema["description"])), ""]
        props = schema.get("properties", {})
        if props:
            required = set(schema.get("required", ()))
            lines += ["| field | type | required | default | meaning |", "|---|---|---|---|---|"]
            for field, s in props.items():
                default = _code(json.dumps(s["default"])) if "default" in s else ""
                lines.append(f"| `{field}` | {_type(s, defs)} | "
                             f"{'yes' if field in required else 'no'} | {default} | "
                             f"{_cell(s.get('description', ''))} |")
            lines.append("")
            if schema.get("additionalProperties") is False:
                lines += ["An unknown field is refused (422).", ""]
    return "\n".join(lines)


# --- machine file -------------------------------------------------------------------------------

def _annotation(tp) -> str:
    """A short name of a type annotation (Annotated metadata dropped)."""
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        return _annotation(typing.get_args(tp)[0])
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_annotation(t) for t in typing.get_args(tp))
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list of {_annotation(args[0])}"
        return "[" + ", ".join(_annotation(t) for t in args) + "]"
    if origin is dict:
        return f"table of {_annotation(typing.get_args(tp)[1])}"
    if tp is type(None):
        return "unset"
    return getattr(tp, "__name__", str(tp))


def _bounds(metadata) -> list[str]:
    """The accepted range of a field from its pydantic constraints."""
    out = []
    for m in metadata:
        out += _bounds(getattr(m, "metadata", ()))  # a Field(...) inside Annotated
        for attr, sign in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<"),
                           ("min_length", "length >="), ("max_length", "length <=")):
            v = getattr(m, attr, None)
            if v is not None:
                out.append(f"{sign} {v:g}" if isinstance(v, float) else f"{sign} {v}")
    return out


def _constraints(tp) -> list[str]:
    """Constraints of a type: its own, those of its Annotated members, tuple items, unions."""
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        args = typing.get_args(tp)
        return _bounds(args[1:]) + _constraints(args[0])
    if origin in (typing.Union, types.UnionType, tuple):
        parts = []
        for t in typing.get_args(tp):
            for c in _constraints(t):
                if c not in parts:
                    parts.append(c)
        return parts
    return []


def _model_of(tp):
    """The pydantic model inside an annotation (``Axis``, ``Limits | None``...), or None."""
    from pydantic import BaseModel

    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return tp
    for t in typing.get_args(tp):
        m = _model_of(t)
        if m is not None:
            return m
    return None


def machine_fields():
    """Every field of a machine file: (path, model, annotation, FieldInfo), depth first.

    A model-valued field is listed, then its own fields under its path; ``axes`` is a table
    of axes whose key (``x``, ``y``, ``z``) is written ``<a>``."""
    from oga.model.machine import Machine

    out = []

    def walk(model, prefix):
        for name, info in model.model_fields.items():
            path = f"{prefix}{name}"
            out.append((path, model, info.annotation, info))
            inner = info.annotation
            if typing.get_origin(inner) is dict:
                inner = typing.get_args(inner)[1]
                path += ".<a>"
            sub = _model_of(inner)
            if sub is not None:
                walk(sub, path + ".")

    walk(Machine, "")
    return out


def machine_markdown() -> str:
    """The machine-file reference: every field with type, default, range and meaning."""
    from pydantic_core import PydanticUndefined

    from oga.defaults import MACHINE_FIELD_RANGES
    from oga.model.machine import PRESETS

    sections: dict[str, tuple[type, list[str]]] = {}
    for path, model, annotation, info in machine_fields():
        if info.default is PydanticUndefined and info.default_factory is None:
            default = "required"
        elif info.default_factory is not None or _model_of(annotation) is not None:
            default = "its fields' defaults" if info.default is not None else "unset"
        elif info.default is None:
            default = "unset"
        else:
            default = _code(json.dumps(info.default))
        rng = ", ".join(_bounds(info.metadata) + _constraints(annotation))
        note = FIELD_NOTES.get(path, info.description or "")
        row = (f"| `{path}` | {_cell(_annotation(annotation))} | {default} | {_cell(rng)} | "
               f"{_cell(note)} |")
        sections.setdefault(path.rsplit(".", 1)[0] if "." in path else "", (model, []))[1].append(row)
    lines = ["# Machine file", "",
             "Generated at build time from the pydantic model `oga.model.machine.Machine` and "
             "`MACHINE_FIELD_RANGES` (`oga/defaults.py`). A machine file is TOML or JSON with "
             "these fields; an unknown key or a value outside its range is refused naming the "
             "field. [Machine files](../howto/machine-files.md) shows how to write one; the "
             f"presets are {', '.join(f'`{p}`' for p in PRESETS)} (`oga/presets/`).", "",
             "`<a>` is an axis name: `x`, `y` or `z`. Each axis has exactly one model, "
             "`cascade` or `arx`; only a cascade axis takes an `uncertainty`.", ""]
    for top, (model, rows) in sections.items():
        lines += [f"## `[{top}]`" if top else "## Top level", ""]
        if model.__doc__:
            lines += [_prose(model.__doc__), ""]
        lines += ["| field | type | default | range | meaning |", "|---|---|---|---|---|",
                  *rows, ""]
    lines += ["## MACHINE_FIELD_RANGES", "",
              "The plausible range of each numeric field (inclusive, SI; gains in (m/min)/mm), "
              "as `oga/defaults.py` holds it; the model above takes its ranges from it.", "",
              "| key | low | high |", "|---|---|---|"]
    lines += [f"| `{k}` | {lo:g} | {hi:g} |" for k, (lo, hi) in MACHINE_FIELD_RANGES.items()]
    return "\n".join(lines) + "\n"


# --- Python API ---------------------------------------------------------------------------------

def python_markdown() -> str:
    """The library reference: mkdocstrings blocks, rendered from the numpydoc docstrings."""
    import oga

    lines = ["# Python API", "",
             "Generated at build time: one block per name `import oga` exports "
             "(`oga.__all__`), then the modules a library user reaches for; each rendered from "
             "its numpydoc docstring. [Your first table](../tutorials/first-table.md#from-python) "
             "shows them at work.", "", "## `oga`", ""]
    for name, module in oga._EXPORTS.items():
        lines += [f"::: {module}.{name}", "    options:", "      heading_level: 3",
                  "      show_root_full_path: false", ""]
    for module in MODULES:
        lines += [f"## `{module}`", "", f"::: {module}", "    options:", "      heading_level: 3",
                  "      show_root_heading: false", "      members_order: source"]
        if module == "oga.defaults":  # its constants carry `#:` comments, not docstrings
            lines.append("      show_if_no_docstring: true")
        lines.append("")
    return "\n".join(lines)


PAGES = {"reference/cli.md": cli_markdown, "reference/rest.md": rest_markdown,
         "reference/machine-file.md": machine_markdown, "reference/python.md": python_markdown}


def on_files(files, config):
    """MkDocs event: add the generated pages to the site's files."""
    from mkdocs.structure.files import File

    for path, make in PAGES.items():
        files.append(File.generated(config, path, content=make()))
    # the history lives in CHANGELOG.md at the root; the site shows it as it is
    files.append(File.generated(config, "changelog.md",
                                content=(ROOT / "CHANGELOG.md").read_text()))
    return files


if __name__ == "__main__":
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "reference-pages")
    for path, make in PAGES.items():
        (out / path).parent.mkdir(parents=True, exist_ok=True)
        (out / path).write_text(make())
        print(out / path)
