"""Pieces of a self-contained HTML page: images as base64 data URIs, line charts as inline SVG, tables.

A report must open anywhere, offline and as a single file, so nothing it shows is fetched: every image is
embedded in the page and every chart is drawn as SVG markup in it. No script runs in the page.
"""
from __future__ import annotations

import base64
import html
import io
import math
from typing import Iterable, Sequence

import numpy as np

STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 70em; padding: 0 1em; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 2em; border-bottom: 1px solid #ccc; }
figure { display: inline-block; margin: 0 1em 1em 0; vertical-align: top; text-align: center; }
figure img { width: 192px; height: 192px; image-rendering: pixelated; border: 1px solid #ccc; }
figcaption { font-size: 0.85em; max-width: 192px; }
table { border-collapse: collapse; margin: 0.5em 0 1em; font-size: 0.9em; }
td, th { border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
.verdict { font-size: 1.3em; font-weight: bold; } .note { color: #666; font-size: 0.9em; }
svg.chart { margin: 0 1em 1em 0; border: 1px solid #ddd; background: #fff; }
"""


def escape(text) -> str:
  return html.escape(str(text), quote=True)


def heading(title: str, level: int = 2) -> str:
  return f"<h{level}>{escape(title)}</h{level}>"


def png_bytes(image) -> bytes:
  """A float image in [0, 1] ([H, W] or [H, W, C]) encoded as 8-bit PNG, as fileio.write_image writes it."""
  import imageio.v3 as iio
  pixels = np.round(np.clip(np.asarray(image, np.float64), 0.0, 1.0) * 255).astype(np.uint8)
  buffer = io.BytesIO()
  iio.imwrite(buffer, pixels, extension=".png")
  return buffer.getvalue()


def png_shape(png: bytes) -> tuple[int, ...]:
  """[H, W(, C)] of a PNG's image."""
  import imageio.v3 as iio
  return iio.imread(png, extension=".png").shape


def data_uri(png: bytes) -> str:
  """A PNG's bytes as a data URI an <img> shows without fetching anything."""
  return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def figure(png: bytes, caption: str) -> str:
  """An embedded PNG with its caption."""
  return (f'<figure><img src="{data_uri(png)}" alt="{escape(caption)}">'
          f"<figcaption>{escape(caption)}</figcaption></figure>")


def number(value) -> str:
  """A table cell's text: floats to 4 significant digits, everything else as it is."""
  if isinstance(value, bool) or not isinstance(value, (int, float)):
    return escape(value)
  return escape(f"{value:.4g}") if isinstance(value, float) else escape(value)


def table(rows: Iterable[Sequence], header: Sequence[str] | None = None) -> str:
  """A table of rows (each a sequence of cells; numbers right-aligned)."""
  head = "<tr>" + "".join(f"<th>{escape(h)}</th>" for h in header) + "</tr>" if header else ""
  body = "".join("<tr>" + "".join(f'<td class="num">{number(c)}</td>' if isinstance(c, (int, float))
                                  and not isinstance(c, bool) else f"<td>{number(c)}</td>" for c in row) + "</tr>"
                 for row in rows)
  return f"<table>{head}{body}</table>"


def flat_items(tree: dict, prefix: str = "") -> list[tuple[str, object]]:
  """(dotted key, value) of every leaf of a nested dict, lists kept as one value; for a table of evidence."""
  items = []
  for name, value in tree.items():
    key = f"{prefix}{name}"
    items += flat_items(value, key + ".") if isinstance(value, dict) else [(key, value)]
  return items


def _ticks(low: float, high: float) -> list[str]:
  """About five round tick values in [low, high] (high > low), as labels with the decimals their spacing needs."""
  unit = 10 ** math.floor(math.log10((high - low) / 4))
  step = unit * next(m for m in (1, 2, 5, 10) if (high - low) / (unit * m) <= 5)
  decimals = max(0, -math.floor(math.log10(step)))
  first = math.ceil(low / step) * step
  return [f"{first + k * step:.{decimals}f}" for k in range(int((high - first) / step + 1e-9) + 1)]


def line_chart(xs: Sequence[float], ys: Sequence[float], title: str, x_label: str = "step", width: int = 420,
               height: int = 220) -> str:
  """An inline SVG line chart of ys [N] against xs [N] (pairs with a non-finite value left out), with its title,
  axis ticks and the last value written beside the title; '' when no pair is finite."""
  points = [(float(x), float(y)) for x, y in zip(xs, ys) if math.isfinite(float(x)) and math.isfinite(float(y))]
  if not points:
    return ""
  left, right, top, bottom = 56, 12, 28, 36
  x_low, x_high = min(p[0] for p in points), max(p[0] for p in points)
  y_low, y_high = min(p[1] for p in points), max(p[1] for p in points)
  if y_high - y_low < 1e-12 * max(1.0, abs(y_high)):
    y_low, y_high = y_low - 0.5 * max(1e-3, abs(y_low)), y_high + 0.5 * max(1e-3, abs(y_high))
  x_high = x_high if x_high > x_low else x_low + 1
  sx = lambda x: left + (x - x_low) / (x_high - x_low) * (width - left - right)
  sy = lambda y: height - bottom - (y - y_low) / (y_high - y_low) * (height - top - bottom)
  parts = [f'<svg class="chart" width="{width}" height="{height}" '
           f'viewBox="0 0 {width} {height}" role="img" aria-label="{escape(title)}">',
           f'<text x="8" y="16" font-size="13">{escape(title)} (last: {points[-1][1]:.4g})</text>',
           f'<line x1="{left}" y1="{height - bottom}" x2="{width - right}" y2="{height - bottom}" stroke="#888"/>',
           f'<line x1="{left}" y1="{top}" x2="{left}" y2="{height - bottom}" stroke="#888"/>']
  for label in _ticks(y_low, y_high):
    y = sy(float(label))
    parts.append(f'<text x="{left - 4}" y="{y + 4:.1f}" font-size="10" text-anchor="end">{label}</text>')
    parts.append(f'<line x1="{left}" y1="{y:.1f}" x2="{width - right}" y2="{y:.1f}" stroke="#eee"/>')
  for label in _ticks(x_low, x_high):
    parts.append(f'<text x="{sx(float(label)):.1f}" y="{height - bottom + 14}" font-size="10" '
                 f'text-anchor="middle">{label}</text>')
  parts.append(f'<text x="{(left + width - right) / 2}" y="{height - 6}" font-size="11" '
               f'text-anchor="middle">{escape(x_label)}</text>')
  if len(points) == 1:
    parts.append(f'<circle cx="{sx(points[0][0]):.1f}" cy="{sy(points[0][1]):.1f}" r="3" fill="#1f77b4"/>')
  else:
    path = " ".join(f"{sx(x):.1f},{sy(y):.1f}" for x, y in points)
    parts.append(f'<polyline fill="none" stroke="#1f77b4" stroke-width="1.5" points="{path}"/>')
  return "".join(parts) + "</svg>"


def document(title: str, body: Sequence[str]) -> str:
  """A whole HTML page: the style inline, `body` the page's sections in order."""
  return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
          f"<title>{escape(title)}</title><style>{STYLE}</style></head>\n<body>\n<h1>{escape(title)}</h1>\n"
          + "\n".join(body) + "\n</body></html>\n")
