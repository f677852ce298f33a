// Line plots on a canvas: axes with round ticks, legend, vertical markers, a cursor readout,
// drag-to-zoom (a box; a flat drag zooms time or frequency only) and double-click to reset.
"use strict";

function niceStep(range, count) {
  const raw = range / Math.max(count, 1);
  const power = Math.pow(10, Math.floor(Math.log10(raw)));
  const unit = raw / power;
  return (unit < 1.5 ? 1 : unit < 3.5 ? 2 : unit < 7.5 ? 5 : 10) * power;
}

function ticks(lo, hi, count) {
  const step = niceStep(hi - lo, count);
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  return {values: out, decimals: Math.max(0, -Math.floor(Math.log10(step) + 1e-9))};
}

function formatValue(v) {
  if (v === null || !isFinite(v)) return "–";
  const a = Math.abs(v);
  if (a !== 0 && (a < 1e-3 || a >= 1e5)) return v.toExponential(2);
  return v.toFixed(a >= 100 ? 1 : a >= 1 ? 3 : 4);
}

class Plot {
  constructor(canvas) {
    this.canvas = canvas;
    this.series = [];
    this.markers = [];
    this.view = null;   // {x0, x1, y0, y1}; null: home
    this.home = null;   // {x0, x1}: the first view (null: all the data)
    this.box = null;
    this.hover = null;
    this.pad = {l: 64, r: 14, t: 30, b: 44};
    this.labels = {x: "", y: "", title: ""};
    canvas.addEventListener("mousedown", (e) => {
      const p = this.point(e);
      if (e.button !== 0 || !this.inside(p)) return;
      this.box = {a: p, b: p};
      e.preventDefault();
    });
    window.addEventListener("mousemove", (e) => {
      const p = this.point(e);
      if (this.box) this.box.b = p;
      this.hover = this.inside(p) ? p : null;
      if (this.box || e.target === canvas || this.hover === null) this.draw();
    });
    window.addEventListener("mouseup", () => {
      if (!this.box) return;
      const {a, b} = this.box;
      this.box = null;
      if (Math.abs(b.x - a.x) > 4) {
        const v = this.current();
        const x0 = this.xOf(Math.min(a.x, b.x), v), x1 = this.xOf(Math.max(a.x, b.x), v);
        if (Math.abs(b.y - a.y) > 4) {
          this.view = {x0, x1, y0: this.yOf(Math.max(a.y, b.y), v), y1: this.yOf(Math.min(a.y, b.y), v)};
        } else {
          this.view = {x0, x1, ...this.yRange(x0, x1)};
        }
      }
      this.draw();
    });
    canvas.addEventListener("dblclick", () => { this.view = null; this.draw(); });
    canvas.addEventListener("mouseleave", () => { this.hover = null; this.draw(); });
    if (window.ResizeObserver) new ResizeObserver(() => this.draw()).observe(canvas);
  }

  set({series, markers = [], x = "", y = "", title = "", home = null}) {
    this.series = series;
    this.markers = markers;
    this.labels = {x, y, title};
    this.home = home;
    this.view = null;
    this.draw();
  }

  point(e) {
    const r = this.canvas.getBoundingClientRect();
    return {x: e.clientX - r.left, y: e.clientY - r.top};
  }

  inside(p) {
    const {l, r, t, b} = this.pad;
    return p.x >= l && p.x <= this.w - r && p.y >= t && p.y <= this.h - b;
  }

  extent() {
    let lo = Infinity, hi = -Infinity;
    for (const s of this.series) for (let i = 0; i < s.x.length; i++) {
      const v = s.x[i];
      if (v !== null && s.y[i] !== null) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
    }
    return isFinite(lo) ? {x0: lo, x1: hi > lo ? hi : lo + 1} : {x0: 0, x1: 1};
  }

  yRange(x0, x1) {
    let lo = Infinity, hi = -Infinity;
    for (const s of this.series) for (let i = 0; i < s.x.length; i++) {
      const x = s.x[i], y = s.y[i];
      if (x === null || y === null || x < x0 || x > x1) continue;
      lo = Math.min(lo, y); hi = Math.max(hi, y);
    }
    if (!isFinite(lo)) return {y0: -1, y1: 1};
    const pad = hi > lo ? 0.06 * (hi - lo) : Math.max(Math.abs(hi) * 0.1, 1e-6);
    return {y0: lo - pad, y1: hi + pad};
  }

  current() {
    if (this.view) return this.view;
    const x = this.home || this.extent();
    return {x0: x.x0, x1: x.x1, ...this.yRange(x.x0, x.x1)};
  }

  // Each visible marker's label box, none overlapping another or the legend: beside its line
  // (right, else left), in the first free row from the top; a label with no free place is left
  // out (the legend names the peaks too). Kept in this.labelBoxes.
  layoutLabels(ctx, v) {
    const {l, r, t, b} = this.pad;
    const right = this.w - r, bottom = this.h - b;
    const taken = this.legendBox ? [this.legendBox] : [];
    const overlaps = (p, q) => p.x < q.x + q.w && q.x < p.x + p.w && p.y < q.y + q.h && q.y < p.y + p.h;
    const visible = this.markers.filter((m) => m.x !== null && m.x >= v.x0 && m.x <= v.x1)
      .map((m) => ({m, X: this.px(m.x, v)})).sort((p, q) => p.X - q.X);
    ctx.font = "11px system-ui, sans-serif";
    for (const item of visible) {
      const w = ctx.measureText(item.m.label).width + 4, h = 14;
      item.box = null;
      for (let y = t + 3; y + h <= bottom && !item.box; y += h + 2) {
        for (const x of [item.X + 2, item.X - 2 - w]) {
          const box = {x, y, w, h};
          if (x >= l && x + w <= right && !taken.some((q) => overlaps(box, q))) { item.box = box; break; }
        }
      }
      if (item.box) taken.push(item.box);
    }
    this.labelBoxes = visible.filter((item) => item.box).map((item) => ({label: item.m.label, ...item.box}));
    return visible;
  }

  px(x, v) { return this.pad.l + (x - v.x0) / (v.x1 - v.x0) * (this.w - this.pad.l - this.pad.r); }
  py(y, v) { return this.h - this.pad.b - (y - v.y0) / (v.y1 - v.y0) * (this.h - this.pad.t - this.pad.b); }
  xOf(px, v) { return v.x0 + (px - this.pad.l) / (this.w - this.pad.l - this.pad.r) * (v.x1 - v.x0); }
  yOf(py, v) { return v.y0 + (this.h - this.pad.b - py) / (this.h - this.pad.t - this.pad.b) * (v.y1 - v.y0); }

  draw() {
    const c = this.canvas, dpr = window.devicePixelRatio || 1;
    this.w = c.clientWidth; this.h = c.clientHeight;
    if (!this.w || !this.h) return;
    if (c.width !== Math.round(this.w * dpr) || c.height !== Math.round(this.h * dpr)) {
      c.width = Math.round(this.w * dpr); c.height = Math.round(this.h * dpr);
    }
    const ctx = c.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#fff";
    ctx.fillRect(0, 0, this.w, this.h);
    const v = this.current();
    const {l, r, t, b} = this.pad;
    const right = this.w - r, bottom = this.h - b;
    ctx.font = "11px system-ui, sans-serif";
    ctx.lineWidth = 1;
    const xt = ticks(v.x0, v.x1, Math.max(3, Math.floor((right - l) / 80)));
    const yt = ticks(v.y0, v.y1, Math.max(3, Math.floor((bottom - t) / 40)));
    ctx.strokeStyle = "#e6e8ec";
    ctx.fillStyle = "#4b5563";
    ctx.textAlign = "center"; ctx.textBaseline = "top";
    for (const x of xt.values) {
      const X = Math.round(this.px(x, v)) + 0.5;
      ctx.beginPath(); ctx.moveTo(X, t); ctx.lineTo(X, bottom); ctx.stroke();
      ctx.fillText(x.toFixed(xt.decimals), X, bottom + 5);
    }
    ctx.textAlign = "right"; ctx.textBaseline = "middle";
    for (const y of yt.values) {
      const Y = Math.round(this.py(y, v)) + 0.5;
      ctx.beginPath(); ctx.moveTo(l, Y); ctx.lineTo(right, Y); ctx.stroke();
      ctx.fillText(y.toFixed(yt.decimals), l - 6, Y);
    }
    ctx.strokeStyle = "#9ca3af";
    ctx.strokeRect(l + 0.5, t + 0.5, right - l, bottom - t);
    ctx.fillStyle = "#1f2937";
    ctx.font = "12px system-ui, sans-serif";
    ctx.textAlign = "center"; ctx.textBaseline = "bottom";
    ctx.fillText(this.labels.x, (l + right) / 2, this.h - 4);
    ctx.save();
    ctx.translate(14, (t + bottom) / 2); ctx.rotate(-Math.PI / 2);
    ctx.textBaseline = "middle";
    ctx.fillText(this.labels.y, 0, 0);
    ctx.restore();
    ctx.font = "600 13px system-ui, sans-serif";
    ctx.textAlign = "left"; ctx.textBaseline = "middle";
    ctx.fillText(this.labels.title, l, t / 2);

    ctx.font = "11px system-ui, sans-serif";
    const legendWidth = Math.max(0, ...this.series.map((s) => ctx.measureText(s.name).width)) + 34;
    this.legendBox = this.series.length
      ? {x: right - legendWidth - 6, y: t + 4, w: legendWidth, h: 16 * this.series.length + 2} : null;
    const placed = this.layoutLabels(ctx, v);
    ctx.save();
    ctx.beginPath(); ctx.rect(l, t, right - l, bottom - t); ctx.clip();
    for (const {m, X, box} of placed) {
      ctx.strokeStyle = m.color; ctx.setLineDash([5, 4]);
      ctx.beginPath(); ctx.moveTo(X, t); ctx.lineTo(X, bottom); ctx.stroke();
      ctx.setLineDash([]);
      if (!box) continue;
      ctx.font = "11px system-ui, sans-serif";
      ctx.textAlign = "left"; ctx.textBaseline = "top";
      ctx.fillStyle = "rgba(255,255,255,0.85)";
      ctx.fillRect(box.x, box.y, box.w, box.h);
      ctx.fillStyle = m.color;
      ctx.fillText(m.label, box.x + 2, box.y + 1);
    }
    ctx.lineWidth = 1.4;
    ctx.lineJoin = "round";
    for (const s of this.series) {
      ctx.strokeStyle = s.color;
      ctx.beginPath();
      let pen = false;
      for (let i = 0; i < s.x.length; i++) {
        if (s.x[i] === null || s.y[i] === null) { pen = false; continue; }
        const X = this.px(s.x[i], v), Y = this.py(s.y[i], v);
        if (pen) ctx.lineTo(X, Y); else ctx.moveTo(X, Y);
        pen = true;
      }
      ctx.stroke();
    }
    ctx.restore();

    // Legend (top right, inside the axes)
    ctx.font = "11px system-ui, sans-serif";
    ctx.textAlign = "left"; ctx.textBaseline = "middle";
    const width = legendWidth;
    let y = t + 12;
    if (this.legendBox) {
      const g = this.legendBox;
      ctx.fillStyle = "rgba(255,255,255,0.85)";
      ctx.fillRect(g.x, g.y, g.w, g.h);
    }
    for (const s of this.series) {
      ctx.strokeStyle = s.color; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.moveTo(right - width, y); ctx.lineTo(right - width + 18, y); ctx.stroke();
      ctx.fillStyle = "#1f2937";
      ctx.fillText(s.name, right - width + 24, y);
      y += 16;
    }
    ctx.lineWidth = 1;
    if (this.hover) {
      ctx.fillStyle = "#4b5563";
      ctx.textAlign = "right";
      ctx.fillText(`${formatValue(this.xOf(this.hover.x, v))}, ${formatValue(this.yOf(this.hover.y, v))}`, right, t / 2);
    }
    if (this.box) {
      const {a, b: e} = this.box;
      const flat = Math.abs(e.y - a.y) <= 4;
      ctx.fillStyle = "rgba(37,99,235,0.12)"; ctx.strokeStyle = "rgba(37,99,235,0.7)";
      const y0 = flat ? t : Math.min(a.y, e.y), hh = flat ? bottom - t : Math.abs(e.y - a.y);
      ctx.fillRect(Math.min(a.x, e.x), y0, Math.abs(e.x - a.x), hh);
      ctx.strokeRect(Math.min(a.x, e.x) + 0.5, y0 + 0.5, Math.abs(e.x - a.x), hh);
    }
  }
}

window.Plot = Plot;
