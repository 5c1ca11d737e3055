"""Pages the documentation makes from the code at build time, so they never drift from it:

- ``_generated/rest-routes.md``: every route of the REST API from the app's OpenAPI schema,
  with the scope, lock and audit the route table (``backend/api/access.py``) gives it, and
  every request and response body's fields;
- ``_generated/benchmarks.md``: the benchmark tables, from ``benchmarks/results/*.json``.

Run by ``conf.py``; ``python docs/make_pages.py`` writes them alone.
"""

from __future__ import annotations

import ast
import json
import re
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
OUT = Path(__file__).resolve().parent / "_generated"


def _type(schema: dict[str, Any]) -> str:
    """A schema's type in a few characters: ``number``, ``list[RoiIn]``, ``string | null``."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return f"[{name}](#{name.lower()})"
    if "anyOf" in schema:
        return " \\| ".join(_type(s) for s in schema["anyOf"])
    if schema.get("type") == "array":
        items = schema.get("items") or schema.get("prefixItems") or {}
        if isinstance(items, list):
            return "[" + ", ".join(_type(i) for i in items) + "]"
        return f"list[{_type(items)}]"
    if "enum" in schema:
        return " \\| ".join(f"`{v}`" for v in schema["enum"])
    if "const" in schema:
        return f"`{schema['const']}`"
    return str(schema.get("type", "any"))


def _cell(text: object) -> str:
    return str(text).replace("\n", " ").replace("|", "\\|")


def _fields(schema: dict[str, Any]) -> list[str]:
    required = set(schema.get("required", []))
    rows = ["| field | type | required | what |", "| --- | --- | --- | --- |"]
    for name, prop in schema.get("properties", {}).items():
        what = prop.get("description", "")
        if "default" in prop and prop["default"] not in (None, [], {}):
            what = f"{what} (default `{json.dumps(prop['default'])}`)".strip()
        rows.append(
            f"| `{name}` | {_type(prop)} | {'yes' if name in required else ''} | {_cell(what)} |"
        )
    return rows if len(rows) > 2 else ["(no fields)"]


def rest_routes() -> str:
    from backend.api.access import ROUTES
    from backend.api.app import create_app
    from backend.settings import Settings

    schema = create_app(Settings(data_dir=OUT / "nowhere")).openapi()
    lines = [
        "<!-- made by docs/make_pages.py from the app's OpenAPI schema and route table -->",
        "",
        "## Routes",
        "",
        "| method | path | scope | lock | audited | what |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    operations = []
    for path, methods in schema["paths"].items():
        for method, op in methods.items():
            access = ROUTES[(method.upper(), path)]
            lock = "abort always" if access.safety else "423 if held" if access.lock else ""
            summary = op.get("summary", "")
            lines.append(
                f"| {method.upper()} | `{path}` | {access.scope or 'anyone'} | {lock} | "
                f"{'yes' if access.audit else ''} | {_cell(summary)} |"
            )
            operations.append((method, path, op))
    lines += ["", "## Each route", ""]
    for method, path, op in operations:
        lines += [f"### {method.upper()} {path}", ""]
        if op.get("description"):
            lines += [op["description"].strip(), ""]
        params = op.get("parameters", [])
        if params:
            lines += [
                "| parameter | in | type | required | what |",
                "| --- | --- | --- | --- | --- |",
            ]
            for p in params:
                lines.append(
                    f"| `{p['name']}` | {p['in']} | {_type(p.get('schema', {}))} | "
                    f"{'yes' if p.get('required') else ''} | {_cell(p.get('description', ''))} |"
                )
            lines.append("")
        body = op.get("requestBody", {}).get("content", {})
        for media, content in body.items():
            lines += [f"Body ({media}): {_type(content.get('schema', {}))}", ""]
        for status, answer in op.get("responses", {}).items():
            if status.startswith("2"):
                content = answer.get("content", {})
                shown = ", ".join(f"{m}: {_type(c.get('schema', {}))}" for m, c in content.items())
                lines += [f"Answer {status}: {shown or answer.get('description', '')}", ""]
    lines += ["## Bodies", ""]
    for name, body_schema in schema.get("components", {}).get("schemas", {}).items():
        lines += [f"### {name}", ""]
        if body_schema.get("description"):
            lines += [_cell(body_schema["description"]), ""]
        lines += [*_fields(body_schema), ""]
    return "\n".join(lines) + "\n"


def _flat(value: Any, prefix: str = "") -> dict[str, Any]:
    """A nested record as one row: ``{"a": {"b": 1}}`` -> ``{"a.b": 1}``."""
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return {k.rstrip("."): v for k, v in out.items()}
    return {prefix: value}


def _number(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        return f"{len(value)} records (in the JSON)"  # a case's draws: the row is their summary
    if isinstance(value, list):
        return (
            "[" + ", ".join(_number(v) for v in value[:6]) + (", …" if len(value) > 6 else "") + "]"
        )
    return _cell(value)


def _explode(record: dict[str, Any]) -> list[dict[str, Any]]:
    """A record holding a mapping of named records (``{"case": .., "methods": {"default":
    {..}, ..}}``) as one row per name (``case``, ``method``, its fields), so that a table
    has a column per measurement instead of one per measurement and name."""
    for key, value in record.items():
        if isinstance(value, dict) and value and all(isinstance(v, dict) for v in value.values()):
            rest = {k: v for k, v in record.items() if k != key}
            label = key[:-1] if key.endswith("s") else key
            return [{**rest, label: name, **inner} for name, inner in value.items()]
    return [record]


def _table(rows: list[dict[str, Any]]) -> list[str]:
    columns: list[str] = []
    for row in rows:
        columns += [c for c in row if c not in columns]
    lines = ["| " + " | ".join(columns) + " |", "|" + " --- |" * len(columns)]
    for row in rows:
        lines.append("| " + " | ".join(_number(row.get(c, "")) for c in columns) + " |")
    return lines


def _scalar(value: Any) -> bool:
    return not isinstance(value, dict | list) or (
        isinstance(value, list) and all(not isinstance(v, dict | list) for v in value)
    )


def _tables(data: Any, title: str) -> list[str]:
    """Every table a result holds: a list of records, or a mapping of names to records, is a
    table (nested records flattened into dotted columns); other scalars go in a key/value
    table; deeper mappings are walked, their keys making the titles."""
    lines: list[str] = []
    if isinstance(data, list) and data and all(isinstance(r, dict) for r in data):
        rows = [_flat(row) for record in data for row in _explode(record)]
        return [f"**{title}**", "", *_table(rows[:200]), ""]
    if not isinstance(data, dict):
        return [f"**{title}**: {_number(data)}", ""]
    scalars = {k: v for k, v in data.items() if _scalar(v)}
    nested = {k: v for k, v in data.items() if not _scalar(v)}
    if scalars:
        lines += [f"**{title}**", "", "| | |", "| --- | --- |"]
        lines += [f"| {_cell(k)} | {_number(v)} |" for k, v in scalars.items()] + [""]
    records = {k: v for k, v in nested.items() if isinstance(v, dict)}
    if records and all(_scalar(x) for v in records.values() for x in v.values()):
        rows = [{"": k, **v} for k, v in records.items()]
        named = f"{title} · {', '.join(records)}" if scalars else title
        lines += [f"**{named}**", "", *_table(rows), ""]
        nested = {k: v for k, v in nested.items() if k not in records}
    for key, value in nested.items():
        lines += _tables(value, f"{title} · {key}")
    return lines


def _scale_plot(data: Any) -> str | None:
    """Time and memory against the number of patches (``merge_scale.json``), as a figure."""
    sizes = [r for r in data.get("sizes", []) if "patches" in r and "wall_s" in r]
    if len(sizes) < 2:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.4), constrained_layout=True)
    for pixels in sorted({r["pixels"] for r in sizes}):
        rows = sorted((r for r in sizes if r["pixels"] == pixels), key=lambda r: r["patches"])
        n = [r["patches"] for r in rows]
        ax.loglog(n, [r["wall_s"] for r in rows], "o-", label=f"time, {pixels} px patches")
        ax.loglog(n, [r["peak_gb"] * 10 for r in rows], "s--", label=f"memory x 10 GB, {pixels} px")
    ax.set(xlabel="patches", ylabel="seconds", title="the CLI's merge, 2 cores")
    ax.legend(fontsize=8)
    fig.savefig(OUT / "merge_scale.png", dpi=110)
    plt.close(fig)
    return "![Time and memory against the number of patches](/_generated/merge_scale.png)"


def _gratings_plot(data: Any) -> str | None:
    """The tip-drawn gratings' XY error over the bound, case by case (``merge_bench.json``)."""
    tips = [r for r in data.get("tip_gratings", []) if "xy_over_crb" in r]
    if not tips:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.4), constrained_layout=True)
    labels = [f"{r['geometry']}, {r['step'] * 1e6:g} µm, {r['pixel'] * 1e9:.0f} nm" for r in tips]
    x = range(len(tips))
    ax.bar(x, [r["xy_over_crb"] for r in tips], color="tab:blue", label="XY / bound")
    ax.plot(
        x,
        [r["map_over_floor_median"] for r in tips],
        "o",
        color="tab:orange",
        label="map / floor, median",
    )
    ax.axhline(1.0, color="0.3", lw=0.8)
    ax.set_yscale("log")
    ax.set_xticks(list(x), labels, rotation=70, fontsize=7)
    ax.set(title="tip-drawn chessboards: geometry, step, pixel")
    ax.legend(fontsize=8)
    fig.savefig(OUT / "merge_bench_gratings.png", dpi=110)
    plt.close(fig)
    return (
        "![The tip-drawn gratings' XY error over the bound](/_generated/merge_bench_gratings.png)"
    )


PLOTS = {"merge_scale": _scale_plot, "merge_bench": _gratings_plot}


def _what(stem: str) -> list[str]:
    """What a benchmark measures: the first paragraph of its script's docstring."""
    script = ROOT / "benchmarks" / f"{stem}.py"
    if not script.exists():
        return []
    doc = ast.get_docstring(ast.parse(script.read_text())) or ""
    first = " ".join(doc.split("\n\n")[0].split())
    first = re.sub(r":\w+:`~?([^`]+)`", r"`\1`", first).replace("``", "`")  # reST roles -> code
    return [first, ""] if first else []


def benchmarks() -> str:
    """One section per ``benchmarks/results/*.json``: its records as tables (and a figure
    where :data:`PLOTS` has one)."""
    found = sorted((ROOT / "benchmarks" / "results").glob("*.json"))
    if not found:
        return "No results yet: `make bench` writes them to `benchmarks/results/`.\n"
    lines = ["<!-- made by docs/make_pages.py from benchmarks/results/*.json -->", ""]
    for path in found:
        data = json.loads(path.read_text())
        lines += [
            f"## {path.stem}",
            "",
            *_what(path.stem),
            f"From `benchmarks/results/{path.name}`.",
            "",
        ]
        plot = PLOTS.get(path.stem)
        figure = plot(data) if plot is not None else None
        if figure:
            lines += [figure, ""]
        lines += _tables(data, path.stem)
    return "\n".join(lines) + "\n"


def _write(name: str, made: str) -> None:
    target = OUT / name
    if not target.exists() or target.read_text() != made:  # unchanged: no rebuild of the page
        target.write_text(made)


def main() -> None:
    sys.path.insert(0, str(ROOT))
    OUT.mkdir(exist_ok=True)
    _write("rest-routes.md", rest_routes())
    _write("benchmarks.md", benchmarks())


if __name__ == "__main__":
    main()
