"""The report's HTML: one self-contained file (images embedded as ``data:`` URIs, no script or style
from the network). A small inline script checks on load that every image decoded (a broken one is
reported with ``console.error``) and writes what it found into ``<pre id="selfcheck">``.
"""
from __future__ import annotations

import base64
import html
from dataclasses import dataclass, field
from typing import Optional, Sequence

CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;margin:0 auto;max-width:1180px;padding:16px;color:#222}
h1{font-size:1.5em;margin:.2em 0}h2{border-bottom:1px solid #ccc;padding-bottom:4px;margin-top:1.6em}
table{border-collapse:collapse;font-size:.9em;margin:.5em 0}td,th{border:1px solid #ddd;padding:3px 8px;text-align:left}
th{background:#f4f4f4}img{max-width:100%;height:auto}.row{display:flex;flex-wrap:wrap;gap:6px;margin:.6em 0}
.row figure{margin:0;flex:1 1 220px}.row figcaption,.note{font-size:.85em;color:#555}
pre{background:#f7f7f7;padding:8px;overflow-x:auto;font-size:.8em}#selfcheck{display:none}
nav a{margin-right:10px}
"""

SELF_CHECK = """
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var broken = imgs.filter(function (i) { return !i.complete || i.naturalWidth === 0; });
  broken.forEach(function (i) { console.error('report: broken image ' + (i.alt || i.src.slice(0, 40))); });
  var sections = Array.prototype.slice.call(document.querySelectorAll('section')).map(function (s) {
    return {id: s.id, height: Math.round(s.getBoundingClientRect().height)}; });
  var sizes = imgs.map(function (i) { return {alt: i.alt, w: i.naturalWidth, h: i.naturalHeight}; });
  document.getElementById('selfcheck').textContent = JSON.stringify(
    {images: imgs.length, broken: broken.length, sections: sections, sizes: sizes});
});
"""


def data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def esc(v: object) -> str:
    return html.escape(str(v), quote=True)


def img_tag(data: bytes, mime: str, alt: str, width: Optional[int] = None) -> str:
    w = f' width="{int(width)}"' if width else ""
    return f'<img src="{data_uri(data, mime)}" alt="{esc(alt)}"{w}>'


def table(rows: Sequence[Sequence[object]], header: Optional[Sequence[str]] = None) -> str:
    out = ["<table>"]
    if header:
        out.append("<tr>" + "".join(f"<th>{esc(h)}</th>" for h in header) + "</tr>")
    for r in rows:
        out.append("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>")
    out.append("</table>")
    return "".join(out)


@dataclass
class Section:
    """One ``<section>``: ``body`` is trusted HTML built with the helpers above."""

    id: str
    title: str
    body: list[str] = field(default_factory=list)

    def add(self, fragment: str) -> "Section":
        self.body.append(fragment)
        return self

    def note(self, text: str) -> "Section":
        return self.add(f'<p class="note">{esc(text)}</p>')


def page(title: str, subtitle: str, sections: Sequence[Section]) -> str:
    nav = " ".join(f'<a href="#{esc(s.id)}">{esc(s.title)}</a>' for s in sections)
    body = "\n".join(f'<section id="{esc(s.id)}"><h2>{esc(s.title)}</h2>\n' + "\n".join(s.body) + "</section>"
                     for s in sections)
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{esc(title)}</title>'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<style>{CSS}</style></head><body><h1>{esc(title)}</h1><p class=\"note\">{esc(subtitle)}</p>"
            f"<nav>{nav}</nav>\n{body}\n<pre id=\"selfcheck\"></pre><script>{SELF_CHECK}</script></body></html>\n")
