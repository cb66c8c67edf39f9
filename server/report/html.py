"""A session report as one self-contained HTML page: inline CSS and SVG, no script, no URL.

Every string that comes from the report (names, materials, notes) is escaped: a recording's
name is the user's, and the page may be served by the control plane.
"""

from __future__ import annotations

from html import escape

from .model import SessionReport
from .svg import CUT_FILL, FORBIDDEN, THRESHOLD, force_plot

CSS = """
body { font: 15px/1.45 system-ui, sans-serif; color: #111827; margin: 2em auto;
       max-width: 920px; padding: 0 1em; }
h1 { font-size: 1.4em; margin-bottom: 0.2em; } h2 { font-size: 1.1em; margin-top: 1.6em; }
.sub { color: #4b5563; margin-top: 0; }
.cards { display: grid; grid-template-columns: repeat(auto-fill, minmax(200px, 1fr));
         gap: 0.6em; }
.card { border: 1px solid #e5e7eb; border-radius: 6px; padding: 0.5em 0.8em; }
.card b { display: block; font-size: 1.35em; }
.card.alert { border-color: #dc2626; background: #fef2f2; }
table { border-collapse: collapse; } td, th { padding: 0.25em 0.8em; text-align: right; }
th { border-bottom: 1px solid #9ca3af; } td:first-child, th:first-child { text-align: left; }
.plot { width: 100%; height: auto; font-size: 11px; }
.key span { display: inline-block; width: 1em; height: 0.8em; margin: 0 0.3em 0 1em; }
.notes { color: #92400e; }
"""


def render_html(report: SessionReport) -> str:
    """The page: headline numbers first, then forbidden contacts, removal per material, the
    force plot and notes."""
    r = report
    e = escape
    alert = " alert" if r.forbidden_contacts else ""
    cards = [
        ("Duration", f"{r.duration_s:.1f} s", ""),
        ("Time cutting", f"{r.cutting_s:.1f} s", ""),
        ("Bone removed", f"{r.removed_mm3:.3g} mm³", ""),
        ("Forbidden contacts", f"{len(r.forbidden_contacts)}", alert),
        ("Peak hand force", f"{r.hand_force_peak_N:.2f} N", ""),
        ("Mean hand force in contact", f"{r.hand_force_mean_N:.2f} N", ""),
        (f"Time above {r.threshold_N:g} N", f"{r.time_above_threshold_s:.2f} s", ""),
    ]
    # A live session's source is already "session N".
    live = r.source_kind == "session"
    sub = [r.source if live else f"{r.source_kind} {r.source}"]
    if r.session_id is not None and not live:
        sub.append(f"session {r.session_id}")
    if r.started_at:
        sub.append(f"started {r.started_at}")
    if not r.complete:
        sub.append("incomplete")
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           f"<title>Session report: {e(r.source)}</title>", f"<style>{CSS}</style></head>",
           "<body>", "<h1>Session report</h1>", f'<p class="sub">{e(" · ".join(sub))}</p>',
           '<div class="cards">']
    out += [f'<div class="card{cls}">{e(label)}<b>{e(value)}</b></div>'
            for label, value, cls in cards]
    out.append("</div>")

    out.append("<h2>Forbidden contacts</h2>")
    if r.forbidden_contacts:
        out.append("<table><tr><th>Time, s</th><th>Structure</th><th>Label</th>"
                   "<th>Position x, y, z (mm)</th></tr>")
        for c in r.forbidden_contacts:
            pos = ", ".join(f"{v:.2f}" for v in c.position_mm)
            out.append(f"<tr><td>{c.time_s:.3f}</td><td>{e(c.material)}</td>"
                       f"<td>{c.label}</td><td>{e(pos)}</td></tr>")
        out.append("</table>")
    else:
        out.append("<p>None.</p>")

    out.append("<h2>Bone removed per material</h2>")
    if r.removed_mm3_by_material:
        out.append("<table><tr><th>Material</th><th>mm³</th></tr>")
        out += [f"<tr><td>{e(name)}</td><td>{v:.4g}</td></tr>"
                for name, v in r.removed_mm3_by_material.items()]
        out.append("</table>")
    else:
        out.append("<p>None.</p>")

    out.append("<h2>Hand force</h2>")
    out.append(force_plot(r.series_t_s, r.series_force_N, r.threshold_N,
                          [c.time_s for c in r.forbidden_contacts], r.cutting_intervals_s))
    out.append(f'<p class="key"><span style="background:{CUT_FILL}"></span>cutting'
               f'<span style="border-top:2px dashed {THRESHOLD}"></span>threshold'
               f'<span style="background:{FORBIDDEN}"></span>forbidden contact</p>')
    counted = "samples of the stream" if live else "ticks"
    out.append(f"<p>The force the replies carried (what the hand was sent), {r.ticks} "
               f"{counted}; the mean is over the {counted} with the burr or shaft in bone.</p>")
    if r.notes:
        out.append("<h2>Notes</h2><ul class=\"notes\">")
        out += [f"<li>{e(n)}</li>" for n in r.notes]
        out.append("</ul>")
    out.append("</body></html>")
    return "\n".join(out)
