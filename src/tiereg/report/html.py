"""One self-contained HTML page: the pictures embedded, readable offline, no scripts."""

from __future__ import annotations

import base64
import html
from typing import Any

STYLE = """
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;margin:2em auto;max-width:1100px;
color:#222;line-height:1.4;padding:0 1em}
h1{font-size:1.5em;margin-bottom:.2em} h2{font-size:1.15em;margin-top:1.6em;
border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:.5em 0} td,th{padding:.2em .7em;border-bottom:1px solid #eee;
text-align:right} th:first-child,td:first-child{text-align:left}
.verdict{padding:.6em 1em;border-radius:6px;font-weight:600;display:inline-block}
.yes{background:#e3f4e6;color:#145a22} .no{background:#fde8e6;color:#8a1c12}
.maps{display:flex;flex-wrap:wrap;gap:1em} .maps figure{margin:0;flex:1 1 480px}
figure{margin:.5em 0} img{max-width:100%}
figcaption{font-size:.85em;color:#555} .muted{color:#666;font-size:.9em}
"""


def escape(v: Any) -> str:
    return html.escape(str(v))


def _fmt(v: Any, spec: str = ".3f") -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return format(v, spec)
    return escape(v)


def image(png: bytes, alt: str, caption: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return (f'<figure><img src="data:image/png;base64,{data}" alt="{escape(alt)}">'
            f"<figcaption>{escape(caption)}</figcaption></figure>")


def stats_table(before: dict[str, Any], after: dict[str, Any], units: str) -> str:
    rows = [("points on the reference", "n_used", "d"), ("median dz", "median_dz", ".3f"),
            ("NMAD dz", "nmad_dz", ".3f"), ("RMSE dz", "rmse_z", ".3f"),
            ("5th percentile", "p05_dz", ".3f"), ("25th percentile", "p25_dz", ".3f"),
            ("75th percentile", "p75_dz", ".3f"), ("95th percentile", "p95_dz", ".3f"),
            ("overlap (share of tie points)", "overlap_fraction", ".1%")]
    out = [f"<table><tr><th>statistic ({escape(units)})</th><th>before the fine stage</th>"
           "<th>after</th></tr>"]
    def cell(v: Any, spec: str) -> str:
        if spec == "d":
            return "-" if v is None else format(int(v), "d")
        return _fmt(v, spec)

    for label, key, spec in rows:
        b, a = before.get(key), after.get(key)
        out.append(f"<tr><td>{escape(label)}</td><td>{cell(b, spec)}</td>"
                   f"<td>{cell(a, spec)}</td></tr>")
    out.append("</table>")
    return "".join(out)


def parameters_table(params: dict[str, Any], precision: dict[str, Any]) -> str:
    out = ["<table><tr><th>parameter</th><th>value</th><th>1 sigma</th></tr>"]
    for key, spec in (("scale", ".8f"), ("omega_deg", ".5f"), ("phi_deg", ".5f"),
                      ("kappa_deg", ".5f")):
        out.append(f"<tr><td>{escape(key)}</td><td>{_fmt(params.get(key), spec)}</td>"
                   f"<td>{_fmt(precision.get(key), '.2e')}</td></tr>")
    t = params.get("translation") or [None] * 3
    s = precision.get("translation") or [None] * 3
    for axis, v, sd in zip("xyz", t, s):
        out.append(f"<tr><td>translation {axis}</td><td>{_fmt(v, '.4f')}</td>"
                   f"<td>{_fmt(sd, '.4f')}</td></tr>")
    out.append("</table>")
    if precision.get("translation_at"):
        at = escape(precision["translation_at"])
        out.append(f'<p class="muted">translation precision at the {at}</p>')
    return "".join(out)


def page(*, data: dict[str, Any], sections: list[tuple[str, str]], title: str) -> str:
    confident = bool(data.get("confident"))
    verdict = (f'<div class="verdict {"yes" if confident else "no"}">'
               f'{"Registered and confident" if confident else "Not confident"} '
               f'(confidence {float(data.get("confidence", 0.0)):.2f})</div>')
    notes = "".join(f"<li>{escape(r)}</li>" for r in data.get("reasons", []))
    warns = "".join(f"<li>{escape(w)}</li>" for w in data.get("warnings", []))
    inputs = data.get("inputs", {})
    version = escape(data.get("tiereg_version", ""))
    head = (f"<h1>{escape(title)}</h1><p class='muted'>tiereg {version}"
            f" &middot; moving: {escape(inputs.get('moving', '?'))} &middot; reference: "
            f"{escape(inputs.get('reference', '?'))} &middot; units: "
            f"{escape(inputs.get('units', '?'))}</p>{verdict}")
    if notes:
        head += f"<h2>Why not confident</h2><ul>{notes}</ul>"
    if warns:
        head += f"<h2>Warnings</h2><ul>{warns}</ul>"
    body = "".join(f"<h2>{escape(name)}</h2>{content}" for name, content in sections)
    return (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
            f"<title>{escape(title)}</title><style>{STYLE}</style></head><body>{head}{body}"
            "</body></html>\n")
