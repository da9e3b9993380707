"""The comparison report: one self-contained HTML file (no network, opens offline).

:func:`write_report` turns the sections of :func:`mfnormal.report.compare.compare_scene`
and the BSDF checks (:func:`mfnormal.report.bsdf_checks.bsdf_checks`) into ``report.html``;
it measures nothing and imports none of the tools that do. Every image is an
embedded base64 PNG, the styles and the script are inline. Per scene it shows an interactive
comparison of any two methods (a slider, or flipping between them), all renders,
zoomed crops of the grazing-angle regions, the supplemental's Figures 2–5
layout (separable vs non-separable, specular vs same-material tangent facet)
and a table of measurements.
"""

from __future__ import annotations

import base64
import datetime
import html
import json
from pathlib import Path

import numpy as np

from mfnormal.files import atomic_write
from mfnormal.io.images import png_bytes

__all__ = ["data_uri", "find_figures", "write_report"]


def data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def find_figures(directory) -> list:
    """``(name, PNG bytes)`` of the ``*.png`` files in ``directory``, sorted by name."""
    directory = Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"validation directory not found: {directory}")
    return [(p.name, p.read_bytes()) for p in sorted(directory.glob("*.png"))]


def _fmt(x, digits=3, pct=False):
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    if pct:
        return f"{100.0 * x:.2f} %"
    return f"{x:.{digits}g}" if abs(x) < 1e4 else f"{x:.3e}"


def _pm(se) -> str:
    """`` ± se`` for a stochastic measurement; nothing for a deterministic one."""
    return f" <span class=meta>±{_fmt(se, 1)}</span>" if se > 1e-9 else ""


E = html.escape

STYLE = """
body { font: 14px/1.45 system-ui, -apple-system, "Segoe UI", sans-serif; margin: 0; color: #222; background: #fafafa; }
header, section { max-width: 1280px; margin: 0 auto; padding: 8px 24px; }
header { border-bottom: 1px solid #ddd; }
h1 { font-size: 22px; margin: 12px 0 4px; } h2 { font-size: 19px; margin: 28px 0 6px; border-top: 2px solid #333; padding-top: 10px; }
h3 { font-size: 15px; margin: 18px 0 6px; }
.meta { color: #666; font-size: 12px; }
nav a { margin-right: 14px; }
.ui { display: flex; flex-wrap: wrap; gap: 12px; align-items: center; margin: 6px 0; }
.ui select, .ui button { font: inherit; padding: 2px 6px; }
.viewer { position: relative; display: inline-block; cursor: ew-resize; user-select: none; line-height: 0; border: 1px solid #999; }
.viewer img { display: block; width: 100%; height: auto; image-rendering: pixelated; }
.viewer .img-a { position: absolute; left: 0; top: 0; }
.viewer .divider { position: absolute; top: 0; bottom: 0; width: 2px; margin-left: -1px; background: #fff; box-shadow: 0 0 3px #000; pointer-events: none; }
.viewer .tag { position: absolute; top: 6px; padding: 2px 6px; background: rgba(0,0,0,.6); color: #fff; font-size: 12px; line-height: 1.3; pointer-events: none; }
.viewer .tag-a { left: 6px; } .viewer .tag-b { right: 6px; }
.cropbox { position: absolute; border: 2px solid #ffd400; box-sizing: border-box; pointer-events: none; }
.cropbox span { position: absolute; left: 2px; top: 2px; font-size: 11px; line-height: 1; color: #ffd400; text-shadow: 0 0 2px #000; }
.slider { display: block; margin: 6px 0 0; }
.thumbs { display: flex; flex-wrap: wrap; gap: 10px; }
.thumbs figure { margin: 0; text-align: center; font-size: 12px; cursor: pointer; }
.thumbs img { width: 200px; image-rendering: pixelated; border: 2px solid transparent; }
.thumbs img.is-a { border-color: #d33; } .thumbs img.is-b { border-color: #36c; }
table { border-collapse: collapse; margin: 4px 0; }
.wide { max-width: 100%; overflow-x: auto; }
table.metrics { font-size: 12px; } table.metrics th { white-space: normal; min-width: 4em; }
table.metrics caption { caption-side: top; text-align: left; color: #444; padding: 2px 0 6px; max-width: 1200px; }
th, td { border: 1px solid #ccc; padding: 3px 7px; text-align: right; vertical-align: middle; }
th { background: #eee; } td.l, th.l { text-align: left; } table.metrics td { white-space: nowrap; }
table.crops td, table.fig td { padding: 2px; text-align: center; }
table.crops th { width: 128px; font-size: 12px; }
table.crops img { width: 128px; image-rendering: pixelated; display: block; }
table.fig img.full { width: 400px; image-rendering: pixelated; display: block; }
table.fig .croprow img { width: 130px; image-rendering: pixelated; display: inline-block; margin: 1px; }
.bad { background: #fdd; } .good { background: #dfd; }
.notes { color: #744; }
.thumbs figure.refused { cursor: default; } .thumbs figure.refused div { width: 200px; padding: 8px;
  box-sizing: border-box; border: 2px dashed #bbb; color: #744; text-align: left; }
.refuses { color: #744; white-space: normal; }
figure.val { display: inline-block; margin: 6px; font-size: 12px; } figure.val img { max-width: 600px; display: block; }
dl dt { font-weight: 600; } dl dd { margin: 0 0 6px 18px; }
"""

SCRIPT = r"""
(function () {
  'use strict';
  var active = null;
  function setup(sec) {
    var name = sec.dataset.scene;
    var selA = sec.querySelector('.sel-a'), selB = sec.querySelector('.sel-b');
    var imgA = sec.querySelector('.img-a'), imgB = sec.querySelector('.img-b');
    var tagA = sec.querySelector('.tag-a'), tagB = sec.querySelector('.tag-b');
    var divider = sec.querySelector('.divider'), slider = sec.querySelector('.slider');
    var viewer = sec.querySelector('.viewer'), flipBtn = sec.querySelector('.flip');
    var showing = sec.querySelector('.showing'), boxes = sec.querySelector('.show-crops');
    var state = { mode: 'slider', showA: true };
    function thumb(key) { return document.getElementById('img-' + name + '-' + key); }
    function label(sel) { return sel.options[sel.selectedIndex].text; }
    function update() {
      imgA.src = thumb(selA.value).src; imgB.src = thumb(selB.value).src;
      tagA.textContent = label(selA); tagB.textContent = label(selB);
      var v = parseFloat(slider.value);
      if (state.mode === 'slider') {
        imgA.style.visibility = 'visible';
        imgA.style.clipPath = 'inset(0 ' + (100 - v) + '% 0 0)';
        divider.style.display = 'block'; divider.style.left = v + '%';
        tagA.style.display = 'block'; tagB.style.display = 'block';
        slider.disabled = false; flipBtn.disabled = true;
        showing.textContent = 'left: ' + label(selA) + ' | right: ' + label(selB);
      } else {
        imgA.style.clipPath = 'none';
        imgA.style.visibility = state.showA ? 'visible' : 'hidden';
        divider.style.display = 'none';
        tagA.style.display = state.showA ? 'block' : 'none';
        tagB.style.display = state.showA ? 'none' : 'block';
        slider.disabled = true; flipBtn.disabled = false;
        showing.textContent = 'showing: ' + (state.showA ? label(selA) : label(selB));
      }
      sec.querySelectorAll('.thumb').forEach(function (t) {
        t.classList.toggle('is-a', t.dataset.key === selA.value);
        t.classList.toggle('is-b', t.dataset.key === selB.value);
      });
      sec.querySelectorAll('.cropbox').forEach(function (b) { b.style.display = boxes.checked ? 'block' : 'none'; });
    }
    function flip() { state.showA = !state.showA; update(); }
    selA.addEventListener('change', update); selB.addEventListener('change', update);
    slider.addEventListener('input', update); boxes.addEventListener('change', update);
    flipBtn.addEventListener('click', flip);
    sec.querySelectorAll('input.mode').forEach(function (r) {
      r.addEventListener('change', function () { if (r.checked) { state.mode = r.value; update(); } });
    });
    var dragging = false;
    function fromPointer(e) {
      var r = viewer.getBoundingClientRect();
      slider.value = Math.max(0, Math.min(100, 100 * (e.clientX - r.left) / r.width));
      update();
    }
    viewer.addEventListener('pointerdown', function (e) {
      active = api;
      if (state.mode === 'flip') { flip(); return; }
      dragging = true; viewer.setPointerCapture(e.pointerId); fromPointer(e);
    });
    viewer.addEventListener('pointermove', function (e) { if (dragging) fromPointer(e); });
    viewer.addEventListener('pointerup', function () { dragging = false; });
    sec.querySelectorAll('.thumb').forEach(function (t) {
      t.addEventListener('click', function (e) {
        (e.shiftKey ? selA : selB).value = t.dataset.key; active = api; update();
      });
    });
    sec.addEventListener('pointerenter', function () { active = api; });
    var api = { flip: function () { if (state.mode === 'flip') flip(); } };
    update();
    return api;
  }
  var apis = [];
  document.querySelectorAll('section.scene').forEach(function (s) { apis.push(setup(s)); });
  active = apis[0] || null;
  document.addEventListener('keydown', function (e) {
    if ((e.key === 'f' || e.key === 'F') && active && e.target.tagName !== 'SELECT') active.flip();
  });
})();
"""


#: What the table's relMSE measures, said where it is read.
METRICS_CAPTION = ("relMSE is each method against its own reference (the same method at more samples): "
                   "its noise at this spp, not its distance to the true geometry or to another method "
                   "(that is measured by validation/true_geometry.py against dense meshes of the "
                   "heightfields the maps were baked from; see docs/validation.md).")


def _metrics_table(section, checks_by_key) -> str:
    tilt = 60.0
    head = ("<tr><th class=l>method</th><th>render time</th><th>spp</th><th>reference</th>"
            "<th>noise: relMSE to its own reference<br>(image)</th>"
            "<th>noise: relMSE to its own reference<br>(normal-mapped)</th>"
            "<th>near-black<br>(render)</th><th>near-black<br>(reference)</th>"
            "<th>darkened<br>(reference)</th>"
            f"<th>albedo θ<sub>p</sub>={tilt:g}°<br>θ<sub>i</sub>=0° / 60° / 85°</th>"
            "<th>reciprocity<br>error (max θ<sub>p</sub>)</th><th>NaN/Inf<br>pixels</th>"
            "<th>negative<br>pixels</th></tr>")
    rows = []
    for r in section["results"]:
        m = r["method"]
        c = checks_by_key.get(m.key)
        if c:
            alb = " / ".join(_fmt(c["albedo"].get((tilt, ti)), 3) for ti in (0.0, 60.0, 85.0))
            rec_t = max(c["reciprocity"], key=lambda t: c["reciprocity"][t])
            rec = f"{_fmt(c['reciprocity'][rec_t], 2)}{_pm(c['reciprocity_se'][rec_t])}"
        else:
            alb = rec = "–"
        black_cls = "bad" if r["black"] > 0.005 else "good"
        rows.append(
            f"<tr><td class=l title='{E(m.about)}'>{E(m.label)}</td><td>{r['time']:.1f} s</td>"
            f"<td>{section['spp']}</td><td>{section['ref_spp']} spp, {r['ref_time']:.1f} s</td>"
            f"<td>{_fmt(r['rel_mse'])}</td><td>{_fmt(r['rel_mse_mask'])}</td>"
            f"<td class={black_cls}>{_fmt(r['black'], pct=True)}</td><td>{_fmt(r['black_ref'], pct=True)}</td>"
            f"<td>{_fmt(r['darkened'], pct=True)}</td>"
            f"<td>{alb}</td><td>{rec}</td><td>{r['nonfinite']}</td><td>{r['negative']}</td></tr>")
    rows += [f"<tr class=refused><td class=l title='{E(x['method'].about)}'>{E(x['method'].label)}</td>"
             f"<td class=l colspan=12>{_refusal(x)}</td></tr>" for x in section.get("refused", ())]
    return (f"<div class=wide><table class=metrics><caption>{METRICS_CAPTION}</caption>{head}"
            f"{''.join(rows)}</table></div>")


def _refusal(refused) -> str:
    """What a method that refuses the scene shows in place of its render and measurements."""
    return f"<span class=refuses>refuses this scene: {E(refused['reason'])}</span>"


def _figure_layout(section, uris, crop_uris) -> str:
    """Supplemental Figs. 2–5: rows = tangent facet, columns = separable / non-separable."""
    by_key = {r["method"].key: r for r in section["results"]}
    refused = {x["method"].key: x for x in section.get("refused", ())}
    cols = [("separable", "separable (main paper)"), ("nonseparable", "non-separable (supplemental)")]
    rows = [("specular", "specular tangent facet"), ("same", "same-material tangent facet")]
    if not any(f"{m}_{t}" in by_key or f"{m}_{t}" in refused for m, _ in cols for t, _ in rows):
        return ""
    out = ["<table class=fig><tr><th></th>" + "".join(f"<th>{E(c)}</th>" for _, c in cols) + "</tr>"]
    for t, tl in rows:
        out.append(f"<tr><th class=l>{E(tl)}</th>")
        for m, _ in cols:
            key = f"{m}_{t}"
            if key in refused:
                out.append(f"<td class=l>{_refusal(refused[key])}</td>")
                continue
            if key not in by_key:
                out.append("<td>–</td>")
                continue
            crops = "".join(f"<img src='{u}' alt='{E(key)} crop {i + 1}'>" for i, u in enumerate(crop_uris[key]))
            out.append(f"<td><img class=full src='{uris[key]}' alt='{E(key)}'><div class=croprow>{crops}</div></td>")
        out.append("</tr>")
    out.append("</table>")
    return "".join(out)


def _crop_table(section, results, keys, crop_uris) -> str:
    """The grazing-angle crops, a row per crop and a column per method."""
    if not section["crops"]:
        return "<p>No normal-mapped surface seen at grazing angles.</p>"
    crop_rows = "".join(
        f"<tr><th>{i + 1}</th>" + "".join(f"<td><img src='{crop_uris[k][i]}' alt='{k} crop {i + 1}'></td>" for k in keys) + "</tr>"
        for i in range(len(section["crops"])))
    crop_head = "".join(f"<th>{E(r['method'].label)}</th>" for r in results)
    return f"<table class=crops><tr><th></th>{crop_head}</tr>{crop_rows}</table>"


def _section(section, checks_by_key) -> str:
    name = section["name"]
    results = section["results"]
    W, H = section["width"], section["height"]
    uris = {r["method"].key: data_uri(png_bytes(r["png"])) for r in results}
    crop_uris = {r["method"].key: [data_uri(png_bytes(c)) for c in r["crops"]] for r in results}
    keys = [r["method"].key for r in results]
    a0 = "classic" if "classic" in keys else keys[0]
    b0 = next((k for k in ("nonseparable_specular", "analytic") if k in keys), keys[-1])
    opts = lambda sel: "".join(f"<option value='{k}'{' selected' if k == sel else ''}>"
                               f"{E(r['method'].label)}</option>" for k, r in zip(keys, results))
    scale = max(1, round(640 / W))         # show small renders at ~640 px, pixelated
    boxes = "".join(
        f"<div class=cropbox style='left:{100 * x / W:.3f}%;top:{100 * y / H:.3f}%;"
        f"width:{100 * s / W:.3f}%;height:{100 * s / H:.3f}%'><span>{i + 1}</span></div>"
        for i, (x, y, s) in enumerate(section["crops"]))
    thumbs = "".join(
        f"<figure><img class=thumb id='img-{name}-{k}' data-key='{k}' src='{uris[k]}' "
        f"alt='{E(r['method'].label)}' title='{E(r['method'].about)} (click: right side, "
        f"shift+click: left side)'><figcaption>{E(r['method'].label)}</figcaption></figure>"
        for k, r in zip(keys, results))
    thumbs += "".join(
        f"<figure class=refused id='refused-{name}-{x['method'].key}' title='{E(x['method'].about)}'>"
        f"<div>{_refusal(x)}</div><figcaption>{E(x['method'].label)}</figcaption></figure>"
        for x in section.get("refused", ()))
    crop_table = _crop_table(section, results, keys, crop_uris)
    notes = "".join(f"<p class=notes>Note: {E(n)}</p>" for n in section["notes"])
    return f"""
<section class=scene id='scene-{name}' data-scene='{name}'>
<h2>{E(section['title'] or name)}</h2>
<p class=meta>{E(section['path'])} · {W}×{H} · {section['spp']} spp, references {section['ref_spp']} spp ·
normal-mapped pixels {100 * section['mask_fraction']:.1f} % (of which seen at grazing angles: crops) ·
near-black threshold {section['black_threshold']:.3g}</p>
{notes}
<div class=ui>
<label>left <select class=sel-a>{opts(a0)}</select></label>
<label>right <select class=sel-b>{opts(b0)}</select></label>
<label><input type=radio class=mode name='mode-{name}' value=slider checked> slider</label>
<label><input type=radio class=mode name='mode-{name}' value=flip> flip</label>
<button type=button class=flip disabled>flip (F / click)</button>
<label><input type=checkbox class=show-crops checked> crop boxes</label>
<span class='showing meta'></span>
</div>
<div class=viewer style='width:min(100%, {W * scale}px)'>
<img class=img-b alt='right image' width={W} height={H}><img class=img-a alt='left image' width={W} height={H}>
<div class=divider></div>{boxes}<div class='tag tag-a'></div><div class='tag tag-b'></div>
</div>
<input type=range class=slider min=0 max=100 step=0.5 value=50 aria-label='comparison position' style='width:min(100%, {W * scale}px)'>
<h3>All methods</h3>
<div class=thumbs>{thumbs}</div>
<h3>Grazing-angle crops (boxes above)</h3>
{crop_table}
<h3>Separable vs non-separable, specular vs same-material tangent facet (the supplemental's Figures 2–5)</h3>
{_figure_layout(section, uris, crop_uris)}
<h3>Measurements</h3>
{_metrics_table(section, checks_by_key)}
<figure class=val><img class=mask src='{data_uri(png_bytes(section["mask_png"]))}' alt='{E(name)} mask'
style='width:{min(W, 320)}px;image-rendering:pixelated'><figcaption>normal-mapped pixels (grey; metrics use the
fully covered ones) and those seen at grazing angles (white)</figcaption></figure>
</section>"""


def _checks_section(checks) -> str:
    if not checks:
        return ""
    # The tilts and incidence angles measured (mfnormal.report.bsdf_checks), in their order.
    tilts = list(dict.fromkeys(tp for tp, _ in checks[0]["albedo"]))
    thetas_i = list(dict.fromkeys(ti for _, ti in checks[0]["albedo"]))
    head = "<tr><th class=l>method</th>" + "".join(
        f"<th>albedo θ<sub>p</sub>={tp:g}°<br>θ<sub>i</sub>={ti:g}°</th>" for tp in tilts for ti in thetas_i)
    head += "".join(f"<th>reciprocity<br>θ<sub>p</sub>={tp:g}°</th>" for tp in tilts) + "</tr>"
    rows = []
    for c in checks:
        cells = "".join(
            f"<td class={'bad' if c['albedo'][(tp, ti)] > 1.005 else ''}>{_fmt(c['albedo'][(tp, ti)], 3)}</td>"
            for tp in tilts for ti in thetas_i)
        cells += "".join(f"<td>{_fmt(c['reciprocity'][tp], 2)}{_pm(c['reciprocity_se'][tp])}</td>"
                         for tp in tilts)
        rows.append(f"<tr><td class=l title='{E(c['method'].about)}'>{E(c['method'].label)}</td>{cells}</tr>")
    return f"""
<section id=checks>
<h2>The BSDFs alone: white furnace and reciprocity</h2>
<p>Each method with a white Lambertian nested BSDF under a constant normal map tilted by θ<sub>p</sub>
(azimuth 0°). <b>Albedo</b>: the mean sample weight for ω<sub>i</sub> at θ<sub>i</sub>, on the side away
from the tilt (azimuth 195°); 1 means energy conserving, above 1 gains energy.
<b>Reciprocity error</b>: mean over random direction pairs of |f(i,o) − f(o,i)| / mean(f(i,o), f(o,i)),
f = eval / cos θ<sub>o</sub>; ± is the same ratio for one standard error (the random walks' eval is
stochastic, so their error is noise below about this level).</p>
<table class=checks>{head}{''.join(rows)}</table>
</section>"""


def _validation_section(figures) -> str:
    if not figures:
        return ""
    figs = "".join(f"<figure class=val><img src='{data_uri(b)}' alt='{E(n)}'><figcaption>{E(n)}</figcaption></figure>"
                   for n, b in figures)
    return f"<section id=validation><h2>Validation plots</h2>{figs}</section>"


DEFINITIONS = """
<section id=definitions>
<h2>Definitions</h2>
<dl>
<dt>render time</dt><dd>wall-clock time of the render at the listed spp, including Dr.Jit's kernel
compilation (or its cache look-up); the reference is rendered after it with independent seeds.</dd>
<dt>relMSE</dt><dd>mean over pixels and channels of (x − ref)² / (ref² + 0.01), against the
reference of the same method (not the true geometry, nor another method): the noise of the method at this spp (plus a quarter of it, from the
reference's own noise at 4× spp). "normal-mapped": only pixels fully covered by normal-mapped shapes.</dd>
<dt>near-black</dt><dd>fraction of the pixels fully covered by normal-mapped shapes whose luminance is
below 5 % of the median luminance of those pixels in the flat reference: the black fringes of classic
normal mapping at grazing angles (in the render, and in the reference where noise matters less).</dd>
<dt>darkened</dt><dd>fraction of those pixels whose luminance in the reference is below 10 % of the flat
reference's at the same pixel: energy lost where the flat surface is lit.</dd>
<dt>crops</dt><dd>the windows with the most normal-mapped pixels seen at grazing angles (mean |cos| between
view ray and shading normal below 0.3).</dd>
</dl>
</section>"""


def write_report(path, sections, checks, figures=(), meta=None) -> Path:
    """Write the self-contained HTML report to ``path`` (atomically); returns it."""
    meta = meta or {}
    checks_by_key = {c["method"].key: c for c in checks}
    nav = "".join(f"<a href='#scene-{s['name']}'>{E(s['title'] or s['name'])}</a>" for s in sections)
    nav += "<a href='#checks'>BSDF checks</a>" if checks else ""
    nav += "<a href='#validation'>validation</a>" if figures else ""
    stamp = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    info = " · ".join(f"{k} {E(str(v))}" for k, v in (
        ("Mitsuba", meta.get("mitsuba")), ("Dr.Jit", meta.get("drjit")), ("variant", meta.get("variant")),
        ("threads", meta.get("threads")), ("libLLVM", meta.get("llvm"))) if v is not None)
    total = f" · total {meta['total_time']:.0f} s" if "total_time" in meta else ""
    command = f"<p class=meta><code>{E(meta['command'])}</code></p>" if meta.get("command") else ""
    body = "".join(_section(s, checks_by_key) for s in sections)
    doc = f"""<!DOCTYPE html>
<html lang=en>
<head>
<meta charset=utf-8>
<meta name=viewport content='width=device-width, initial-scale=1'>
<link rel=icon href='data:,'>
<title>mfnormal: normal-mapping methods compared</title>
<style>{STYLE}</style>
</head>
<body>
<header>
<h1>Microfacet-based normal mapping: the methods compared</h1>
<p class=meta>Schüßler, Heitz, Hanika, Dachsbacher: <i>Microfacet-based Normal Mapping for Robust Monte Carlo
Path Tracing</i> (SIGGRAPH Asia 2017), as the Mitsuba 3 plugin <code>normalmap_microfacet</code>, next to
Mitsuba's built-in <code>normalmap</code>. Generated {stamp} · {info}{total}</p>
{command}
<nav>{nav}<a href='#definitions'>definitions</a></nav>
</header>
{body}
{_checks_section(checks)}
{_validation_section(figures)}
{DEFINITIONS}
<script>{SCRIPT}</script>
<script type=application/json id=report-data>{json.dumps({"scenes": [s["name"] for s in sections]})}</script>
</body>
</html>
"""
    return atomic_write(path, lambda p: Path(p).write_text(doc, encoding="utf-8"))
