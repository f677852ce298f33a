// refflow gui: the frame viewer with its drawing tools, the project panel and the run.
// Coordinates sent to the server are raw video pixels, pixel (i, j)'s centre at (i, j), as
// `refflow track --polygon/--between` reads them; the ROI is X,Y,W,H in whole pixels.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const COLOURS = {roi: "#ffd23f", mask: "#3ddc84", background: "#4ea8ff", scale: "#ff5d5d",
                   dx: "#2563eb", dy: "#ea580c"};
  const FILLS = {mask: "rgba(61,220,132,0.28)", background: "rgba(78,168,255,0.25)"};
  const HELP = {
    roi: "ROI: drag a rectangle around the structure; the frames are cropped to it (optional).",
    mask: "POI mask: click the corners of the structure's surface; click the first corner, double-click " +
          "or press Enter to close the polygon. Backspace removes the last corner, Esc drops it.",
    background: "Background: click the corners of something that does not move (a wall, the ground); the " +
                "camera's own motion measured there is removed (optional, dense methods).",
    scale: "Scale: click two points a known distance apart, then type that length in mm on the right.",
    pan: "Pan: drag to move the view. The mouse wheel zooms in any tool; Fit (F) shows the whole frame.",
  };

  const app = {
    info: null, image: null, shown: -1, wanted: 0, loading: false,
    view: {s: 1, ox: 0, oy: 0}, fitted: false, w: 0, h: 0,
    tool: "mask", roi: null, regions: [], background: [], drawing: null, scalePoints: [],
    drag: null, mouse: null, ready: false, running: false, result: null,
    token: 0, attempt: null,  // the page's latest attempt; the server's number of it
  };
  window.refflowApp = app;
  const canvas = $("frame-canvas");
  const timePlot = new window.Plot($("plot-time"));
  const spectrumPlot = new window.Plot($("plot-spectrum"));
  app.plots = {time: timePlot, spectrum: spectrumPlot};

  // -- messages and the API ------------------------------------------------------------------

  // A message of no attempt (a frame that does not load, a polygon closed too early).
  function say(text, kind = "error") {
    const box = $("message");
    box.textContent = text || "";
    box.className = kind;
    box.hidden = !text;
    box.dataset.attempt = "";
  }

  async function api(path, body) {
    const options = body === undefined ? {} : {
      method: "POST", headers: {"Content-Type": "application/json"}, body: JSON.stringify(body)};
    const reply = await fetch(path, options);
    let data;
    try {
      data = await reply.json();
    } catch (err) {
      data = {error: `${reply.status} ${reply.statusText}`};
    }
    if (!reply.ok) {
      const err = new Error(data.error || `${reply.status} ${reply.statusText}`);
      err.reply = data;
      throw err;
    }
    return data;
  }

  // -- the view: image pixels <-> canvas -----------------------------------------------------

  const s = () => app.view.s;
  const pixelToCanvas = (x, y) => [(x + 0.5) * s() + app.view.ox, (y + 0.5) * s() + app.view.oy];
  const edgeToCanvas = (x, y) => [x * s() + app.view.ox, y * s() + app.view.oy];
  function eventPoint(e) {
    const r = canvas.getBoundingClientRect();
    return [e.clientX - r.left, e.clientY - r.top];
  }
  function toPixel(e) {
    const [cx, cy] = eventPoint(e);
    return [(cx - app.view.ox) / s() - 0.5, (cy - app.view.oy) / s() - 0.5];
  }
  function toEdge(e) {
    const [cx, cy] = eventPoint(e);
    return [(cx - app.view.ox) / s(), (cy - app.view.oy) / s()];
  }
  const round2 = (p) => [Math.round(p[0] * 100) / 100, Math.round(p[1] * 100) / 100];
  // For tests and scripts: where raw pixel (x, y) is, in CSS pixels from the canvas's top left.
  app.pixelToClient = (x, y) => pixelToCanvas(x, y);

  function resize() {
    if (!app.info) return;
    const wrap = $("canvas-wrap");
    const w = wrap.clientWidth;
    const aspect = app.info.height / app.info.width;
    const h = Math.max(240, Math.min(Math.round(w * aspect), Math.round(window.innerHeight * 0.6)));
    const dpr = window.devicePixelRatio || 1;
    canvas.style.height = `${h}px`;
    canvas.width = Math.round(w * dpr);
    canvas.height = Math.round(h * dpr);
    app.w = w; app.h = h;
    if (!app.fitted) fit(); else draw();
  }

  function fit() {
    const {width, height} = app.info;
    const scale = Math.min(app.w / width, app.h / height);
    app.view = {s: scale, ox: (app.w - width * scale) / 2, oy: (app.h - height * scale) / 2};
    app.fitted = false;
    draw();
  }

  function zoom(factor, cx, cy) {
    const v = app.view;
    const scale = Math.min(Math.max(v.s * factor, 0.05), 64);
    app.view = {s: scale, ox: cx - (cx - v.ox) * scale / v.s, oy: cy - (cy - v.oy) * scale / v.s};
    app.fitted = true;
    draw();
  }

  // -- drawing ---------------------------------------------------------------------------------

  function roiRect() {
    if (app.drag && app.drag.kind === "roi") {
      const [a, b] = [app.drag.a, app.drag.b];
      const clamp = (v, hi) => Math.min(Math.max(Math.round(v), 0), hi);
      const x0 = clamp(Math.min(a[0], b[0]), app.info.width), x1 = clamp(Math.max(a[0], b[0]), app.info.width);
      const y0 = clamp(Math.min(a[1], b[1]), app.info.height), y1 = clamp(Math.max(a[1], b[1]), app.info.height);
      return [x0, y0, x1 - x0, y1 - y0];
    }
    return Array.isArray(app.roi) && app.roi.length === 4 && app.roi.every(isFinite) ? app.roi : null;
  }

  function polygonPath(ctx, points, close) {
    ctx.beginPath();
    points.forEach((p, i) => {
      const [x, y] = pixelToCanvas(p[0], p[1]);
      if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y);
    });
    if (close) ctx.closePath();
  }

  function label(ctx, text, x, y, colour) {
    ctx.font = "600 12px system-ui, sans-serif";
    const w = ctx.measureText(text).width + 8;
    ctx.fillStyle = "rgba(15,17,21,0.72)";
    ctx.fillRect(x - w / 2, y - 9, w, 18);
    ctx.fillStyle = colour;
    ctx.textAlign = "center"; ctx.textBaseline = "middle";
    ctx.fillText(text, x, y);
  }

  function drawRegion(ctx, region, kind) {
    polygonPath(ctx, region.polygon, true);
    ctx.fillStyle = FILLS[kind];
    ctx.fill();
    ctx.strokeStyle = COLOURS[kind];
    ctx.lineWidth = 1.5;
    ctx.stroke();
    const n = region.polygon.length;
    const cx = region.polygon.reduce((a, p) => a + p[0], 0) / n, cy = region.polygon.reduce((a, p) => a + p[1], 0) / n;
    const [x, y] = pixelToCanvas(cx, cy);
    label(ctx, region.label, x, y, COLOURS[kind]);
  }

  function draw() {
    if (!app.info) return;
    const ctx = canvas.getContext("2d");
    const dpr = window.devicePixelRatio || 1;
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#15171c";
    ctx.fillRect(0, 0, app.w, app.h);
    if (app.image) {
      ctx.save();
      ctx.imageSmoothingEnabled = app.view.s < 3;
      ctx.translate(app.view.ox, app.view.oy);
      ctx.scale(app.view.s, app.view.s);
      ctx.drawImage(app.image, 0, 0);
      ctx.restore();
    }
    const roi = roiRect();
    if (roi) {
      const [x0, y0] = edgeToCanvas(roi[0], roi[1]);
      const [fx, fy] = edgeToCanvas(0, 0);
      ctx.beginPath();
      ctx.rect(fx, fy, app.info.width * s(), app.info.height * s());
      ctx.rect(x0, y0, roi[2] * s(), roi[3] * s());
      ctx.fillStyle = "rgba(0,0,0,0.5)";
      ctx.fill("evenodd");
      ctx.setLineDash([6, 4]);
      ctx.strokeStyle = COLOURS.roi;
      ctx.lineWidth = 1.5;
      ctx.strokeRect(x0, y0, roi[2] * s(), roi[3] * s());
      ctx.setLineDash([]);
      ctx.font = "600 12px system-ui, sans-serif";
      ctx.fillStyle = COLOURS.roi;
      ctx.textAlign = "left"; ctx.textBaseline = "bottom";
      ctx.fillText("ROI", x0 + 2, y0 - 3);
    }
    app.background.forEach((r) => drawRegion(ctx, r, "background"));
    app.regions.forEach((r) => drawRegion(ctx, r, "mask"));
    if (app.drawing) {
      const d = app.drawing;
      const points = app.mouse ? [...d.points, app.mouse] : d.points;
      polygonPath(ctx, points, false);
      ctx.strokeStyle = COLOURS[d.kind];
      ctx.lineWidth = 1.5;
      ctx.setLineDash([4, 3]);
      ctx.stroke();
      ctx.setLineDash([]);
      d.points.forEach((p, i) => {
        const [x, y] = pixelToCanvas(p[0], p[1]);
        ctx.beginPath();
        ctx.arc(x, y, i === 0 ? 5 : 3, 0, 2 * Math.PI);
        ctx.fillStyle = i === 0 ? "#fff" : COLOURS[d.kind];
        ctx.fill();
        ctx.strokeStyle = COLOURS[d.kind];
        ctx.stroke();
      });
    }
    if (app.scalePoints.length) {
      const points = app.scalePoints.map((p) => pixelToCanvas(p[0], p[1]));
      ctx.strokeStyle = COLOURS.scale;
      ctx.lineWidth = 2;
      if (points.length === 2) {
        ctx.beginPath(); ctx.moveTo(...points[0]); ctx.lineTo(...points[1]); ctx.stroke();
      }
      for (const [x, y] of points) {
        ctx.beginPath();
        ctx.moveTo(x - 7, y); ctx.lineTo(x + 7, y); ctx.moveTo(x, y - 7); ctx.lineTo(x, y + 7);
        ctx.stroke();
      }
      if (points.length === 2) {
        const length = $("known-length").value.trim();
        const [a, b] = app.scalePoints;
        const px = Math.hypot(b[0] - a[0], b[1] - a[1]);
        label(ctx, length ? `${length} mm` : `${px.toFixed(1)} px`, (points[0][0] + points[1][0]) / 2,
              (points[0][1] + points[1][1]) / 2 - 14, COLOURS.scale);
      }
    }
  }

  // -- frames ----------------------------------------------------------------------------------

  function showFrame(index) {
    app.wanted = index;
    $("frame-label").textContent = frameText(index);
    if (app.loading) return;
    app.loading = true;
    const image = new Image();
    image.onload = () => {
      app.image = image;
      app.shown = index;
      app.loading = false;
      canvas.dataset.frame = String(index);
      draw();
      if (app.wanted !== index) showFrame(app.wanted);
    };
    image.onerror = async () => {
      app.loading = false;
      try {
        await api(`/api/frame?i=${index}`);
      } catch (err) {
        say(err.message);
      }
    };
    image.src = `/api/frame?i=${index}`;
  }

  function frameText(index) {
    const fps = app.info.fps;
    const time = fps ? `, ${(index / fps).toFixed(2)} s` : "";
    return `frame ${index} / ${Math.max(app.info.frames - 1, 0)}${time}`;
  }

  // -- the regions, the ROI field, the scale ---------------------------------------------------

  function renderRegions() {
    for (const [kind, list, id] of [["mask", app.regions, "regions"], ["background", app.background, "background"]]) {
      const ul = $(id);
      ul.replaceChildren();
      if (!list.length) {
        const li = document.createElement("li");
        li.className = "hint";
        li.textContent = kind === "mask" ? "none: use the POI mask tool" : "none";
        ul.append(li);
      }
      list.forEach((region, i) => {
        const li = document.createElement("li");
        const swatch = document.createElement("span");
        swatch.className = `swatch ${kind}`;
        const input = document.createElement("input");
        input.type = "text";
        input.value = region.label;
        input.setAttribute("aria-label", "region label");
        input.addEventListener("input", () => { region.label = input.value; draw(); });
        const count = document.createElement("span");
        count.className = "hint";
        count.textContent = `${region.polygon.length} corners`;
        const remove = document.createElement("button");
        remove.className = "small";
        remove.textContent = "×";
        remove.title = "remove this region";
        remove.addEventListener("click", () => { list.splice(i, 1); renderRegions(); draw(); });
        li.append(swatch, input, count, remove);
        ul.append(li);
      });
    }
  }

  function setRoi(roi) {
    app.roi = roi;
    $("roi").value = Array.isArray(roi) ? roi.join(",") : (roi || "");
    draw();
  }

  function readRoiField() {
    const text = $("roi").value.trim();
    if (!text) { app.roi = null; draw(); return; }
    const parts = text.split(",").map((v) => v.trim());
    const numbers = parts.map(Number);
    // What is not four integers goes to the tool as typed: its message says what is wrong.
    app.roi = parts.length === 4 && numbers.every(Number.isInteger) ? numbers : text;
    draw();
  }

  function scaleMode() {
    return document.querySelector("input[name=scale-mode]:checked").value;
  }

  function scaleState() {
    const mode = scaleMode();
    if (mode === "length") {
      const length = $("known-length").value.trim();
      if (!length && !app.scalePoints.length) return null;
      return {known_length_mm: length, between_px: app.scalePoints.length === 2 ? app.scalePoints : null};
    }
    if (mode === "mmpx") return {mm_per_px: $("mm-per-px").value.trim()};
    return null;
  }

  // What the scale section says while it gives no mm per pixel of its own.
  function scaleWithout() {
    const mode = scaleMode();
    if (mode === "none") return "displacements in pixels only";
    if (mode === "mmpx") return $("mm-per-px").value.trim() ? "" : "type the mm per pixel, or choose none (pixels only)";
    return scaleState() === null ? "no scale yet: a run now measures in pixels" : "";
  }

  let scaleTimer = null;
  function updateScale() {
    const points = app.scalePoints;
    $("scale-points").textContent = points.length === 2
      ? `(${points[0].map((v) => v.toFixed(1)).join(", ")}) – (${points[1].map((v) => v.toFixed(1)).join(", ")}), ` +
        `${Math.hypot(points[1][0] - points[0][0], points[1][1] - points[0][1]).toFixed(1)} px`
      : points.length === 1 ? "click the second point" : "click two points (Scale tool)";
    clearTimeout(scaleTimer);
    const result = $("scale-result");
    result.classList.remove("bad");
    if (scaleMode() !== "length" || points.length !== 2 || !$("known-length").value.trim()) {
      result.textContent = scaleWithout();
      result.classList.toggle("bad", scaleMode() === "mmpx" && !$("mm-per-px").value.trim());
      draw();
      return;
    }
    scaleTimer = setTimeout(async () => {
      try {
        const r = await api("/api/scale", {known_length_mm: $("known-length").value.trim(), between_px: points});
        result.textContent = `= ${r.mm_per_px.toPrecision(5)} mm per pixel${r.undistorted ? " (undistorted)" : ""}`;
      } catch (err) {
        result.textContent = err.message;
        result.classList.add("bad");
      }
    }, 150);
    draw();
  }

  // -- polygons --------------------------------------------------------------------------------

  // A click this close to the first corner closes the polygon: at most 8 CSS pixels, and at most
  // 5 % of the frame's smaller side as shown, so on a thin frame (40 px high, shown 30 px high) a
  // corner beside the first one is a corner; under 2 px nothing snaps (double-click or Enter closes).
  function snapRadius() {
    const radius = Math.min(8, 0.05 * Math.min(app.info.width, app.info.height) * s());
    return radius >= 2 ? radius : 0;
  }

  // A double-click's clicks add the same corner twice, and a click back on the first corner
  // where nothing snaps adds it again: keep one of each.
  function distinctCorners(points) {
    const apart = (p, q) => Math.hypot(p[0] - q[0], p[1] - q[1]) * s() > 3;
    const kept = points.filter((p, i) => i === 0 || apart(p, points[i - 1]));
    return kept.length > 1 && !apart(kept[kept.length - 1], kept[0]) ? kept.slice(0, -1) : kept;
  }

  function addVertex(p) {
    if (!app.drawing || app.drawing.kind !== app.tool) app.drawing = {kind: app.tool, points: []};
    const d = app.drawing;
    if (distinctCorners(d.points).length >= 3) {
      const [fx, fy] = pixelToCanvas(d.points[0][0], d.points[0][1]);
      const [x, y] = pixelToCanvas(p[0], p[1]);
      if (Math.hypot(fx - x, fy - y) < snapRadius()) { closePolygon(); return; }
    }
    d.points.push(round2(p));
  }

  function hint(text) {
    $("tool-help").textContent = text || HELP[app.tool];
    $("tool-help").classList.toggle("bad", Boolean(text));
  }

  function closePolygon() {
    const d = app.drawing;
    if (!d) return;
    const points = distinctCorners(d.points);
    if (points.length < 3) {
      hint("a polygon needs at least three corners: click more before closing it");
      return;
    }
    const list = d.kind === "mask" ? app.regions : app.background;
    list.push({label: d.kind === "mask" ? `region ${app.regions.length + 1}` : `background ${app.background.length + 1}`,
               polygon: points});
    app.drawing = null;
    hint("");
    renderRegions();
    draw();
  }

  function setTool(tool) {
    if (app.drawing && app.drawing.kind !== tool) {
      if (app.drawing.points.length >= 3) closePolygon(); else app.drawing = null;
    }
    app.tool = tool;
    document.querySelectorAll(".tool").forEach((b) => b.classList.toggle("active", b.dataset.tool === tool));
    canvas.dataset.tool = tool;
    hint("");
    draw();
  }

  // -- canvas events -----------------------------------------------------------------------------

  canvas.addEventListener("mousedown", (e) => {
    if (!app.info) return;
    canvas.focus();
    if (e.button === 1 || e.button === 2 || app.tool === "pan") {
      app.drag = {kind: "pan", x: e.clientX, y: e.clientY, ox: app.view.ox, oy: app.view.oy};
      e.preventDefault();
      return;
    }
    if (e.button !== 0) return;
    if (app.tool === "roi") {
      app.drag = {kind: "roi", a: toEdge(e), b: toEdge(e)};
    } else if (app.tool === "mask" || app.tool === "background") {
      addVertex(toPixel(e));
    } else if (app.tool === "scale") {
      if (app.scalePoints.length >= 2) app.scalePoints = [];
      app.scalePoints.push(round2(toPixel(e)));
      updateScale();
    }
    draw();
  });

  canvas.addEventListener("mousemove", (e) => {
    if (!app.info) return;
    const [x, y] = toPixel(e);
    app.mouse = [x, y];
    const inside = x >= -0.5 && y >= -0.5 && x < app.info.width - 0.5 && y < app.info.height - 0.5;
    $("cursor-readout").textContent = inside ? `x ${Math.round(x)}, y ${Math.round(y)}` : "";
    if (app.drawing) draw();
  });
  canvas.addEventListener("mouseleave", () => { app.mouse = null; $("cursor-readout").textContent = ""; draw(); });

  window.addEventListener("mousemove", (e) => {
    if (!app.drag) return;
    if (app.drag.kind === "pan") {
      app.view.ox = app.drag.ox + e.clientX - app.drag.x;
      app.view.oy = app.drag.oy + e.clientY - app.drag.y;
      app.fitted = true;
    } else if (app.drag.kind === "roi") {
      app.drag.b = toEdge(e);
    }
    draw();
  });

  window.addEventListener("mouseup", () => {
    if (app.drag && app.drag.kind === "roi") {
      const roi = roiRect();
      app.drag = null;
      if (roi[2] >= 2 && roi[3] >= 2) setRoi(roi);
    }
    app.drag = null;
    draw();
  });

  canvas.addEventListener("dblclick", (e) => {
    if (app.drawing) { e.preventDefault(); closePolygon(); }
  });
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const [cx, cy] = eventPoint(e);
    zoom(Math.pow(1.2, -e.deltaY / 100), cx, cy);
  }, {passive: false});

  document.addEventListener("keydown", (e) => {
    const typing = ["INPUT", "TEXTAREA", "SELECT"].includes(document.activeElement.tagName);
    if (typing) return;
    if (e.key === "Enter" && app.drawing) { closePolygon(); e.preventDefault(); }
    else if (e.key === "Escape") { app.drawing = null; draw(); }
    else if (e.key === "Backspace" && app.drawing) { app.drawing.points.pop(); draw(); e.preventDefault(); }
    else if (e.key === "f" || e.key === "F") fit();
    else if (e.key === "ArrowRight" || e.key === "ArrowLeft") {
      const slider = $("frame-slider");
      slider.value = String(Number(slider.value) + (e.key === "ArrowRight" ? 1 : -1));
      showFrame(Number(slider.value));
      e.preventDefault();
    }
  });

  // -- the project ---------------------------------------------------------------------------------

  function project() {
    return {
      roi: app.roi,
      regions: app.regions,
      background: app.background,
      scale: scaleState(),
      method: $("method").value,
      options: {
        preset: $("method").value === "dis" ? $("preset").value : "",
        reference_frame: $("reference-frame").value.trim(),
        reference_average: $("reference-average").value.trim(),
        grid_step: $("grid-step").value.trim(),
        max_frames: $("max-frames").value.trim(),
        filter: $("filter").value,
        jobs: $("jobs").value.trim(),
        params: $("params").value,
      },
    };
  }

  function request() {
    return {name: $("run-name").value.trim(), project: project()};
  }

  function load(saved) {
    app.roi = saved.roi || null;
    $("roi").value = app.roi ? app.roi.join(",") : "";
    app.regions = saved.regions || [];
    app.background = (saved.background && saved.background.regions) || [];
    const scale = saved.scale;
    if (scale && scale.mm_per_px !== undefined) {
      document.querySelector("input[value=mmpx]").checked = true;
      $("mm-per-px").value = scale.mm_per_px;
    } else if (scale) {
      $("known-length").value = scale.known_length_mm;
      const b = scale.between_px;
      app.scalePoints = [[b[0], b[1]], [b[2], b[3]]];
    }
    if (saved.method) $("method").value = saved.method;
    const o = saved.options || {};
    for (const [key, id] of [["preset", "preset"], ["reference_frame", "reference-frame"],
      ["reference_average", "reference-average"], ["grid_step", "grid-step"], ["max_frames", "max-frames"],
      ["filter", "filter"], ["jobs", "jobs"]]) {
      if (o[key] !== undefined) $(id).value = o[key];
    }
    if (o.params) $("params").value = o.params.join("\n");
    renderRegions();
    methodChanged();
    updateScale();
  }

  // -- attempts: a save, a POI figure or a run; the page shows one at a time --------------------
  // The status line, the message box, the command and the result all come from the latest
  // attempt: a new one clears them first, and a reply of an older one is dropped.

  const KINDS = {save: "save", pois: "POI figure", run: "run"};

  function beginAttempt() {
    app.token += 1;
    app.attempt = null;
    clearResults();
    for (const id of ["run-status", "message", "command"]) $(id).dataset.attempt = "pending";
    $("run-status").textContent = "";
    $("run-status").dataset.state = "pending";
    $("message").hidden = true;
    $("message").textContent = "";
    $("command").replaceChildren("…");
    $("progress").value = 0;
    return app.token;
  }

  function clearResults() {
    app.result = null;
    $("results").hidden = true;
    $("results").dataset.ready = "";
    $("downloads").replaceChildren();
    $("units-note").hidden = true;
    timePlot.set({series: []});
    spectrumPlot.set({series: []});
    $("pois-panel").hidden = true;
    $("pois-image").removeAttribute("src");
    $("pois-message").textContent = "";
  }

  function commandLines(groups) {
    // Each option with its value is one unbreakable piece; the line wraps at the spaces between.
    const line = document.createElement("span");
    line.className = "line";
    groups.forEach((group, i) => {
      const piece = document.createElement("span");
      piece.className = "arg";
      piece.textContent = group;
      line.append(...(i ? [" ", piece] : [piece]));
    });
    return line;
  }

  function showAttempt(a) {
    app.attempt = a.attempt;
    const tag = a.attempt ? `${KINDS[a.kind] || a.kind} #${a.attempt}` : (KINDS[a.kind] || "");
    for (const id of ["run-status", "message", "command"]) $(id).dataset.attempt = String(a.attempt || "");
    const status = $("run-status");
    status.dataset.state = a.state;
    const failed = a.state === "failed";
    status.textContent = failed ? `${tag}: failed (the message above says why)` : `${tag}: ${a.message || a.state}`;
    const box = $("message");
    box.textContent = failed || a.state === "cancelled" ? a.message : "";
    box.className = failed ? "error" : "info";
    box.hidden = !box.textContent;
    const command = $("command");
    if (!a.groups) {
      command.replaceChildren(`${tag} was refused before a command was made: see the message above.`);
      delete command.dataset.argv;
      return;
    }
    const parts = [commandLines(a.groups)];
    const saved = {saved: "# or, from the saved project:", done: "# or, from the saved project:",
                   running: "# once the run succeeds, from its saved project:"}[a.state];
    if (saved && a.project_groups) parts.push(`\n\n${saved}\n`, commandLines(a.project_groups));
    command.replaceChildren(...parts);
    command.dataset.argv = JSON.stringify(a.argv);
  }

  function failedAttempt(err, kind) {
    return {kind, ...(err.reply || {}), state: "failed", message: err.message};
  }

  function methodChanged() {
    const method = app.info.methods.find((m) => m.name === $("method").value);
    $("method-summary").textContent = method ? `[${method.kind}] ${method.summary}` : "";
    $("preset-row").hidden = $("method").value !== "dis";
  }

  function setRunning(running) {
    app.running = running;
    $("run").disabled = running;
    $("save").disabled = running;
    $("show-pois").disabled = running;
    $("cancel").disabled = !running;
    document.body.classList.toggle("running", running);
  }

  async function save() {
    const token = beginAttempt();
    try {
      const saved = await api("/api/project", request());
      if (token === app.token) showAttempt(saved);
    } catch (err) {
      if (token === app.token) showAttempt(failedAttempt(err, "save"));
    }
  }

  async function showPois() {
    const token = beginAttempt();
    $("run-status").textContent = "drawing the POIs and KLT's corners…";
    try {
      const r = await api("/api/pois", request());
      if (token !== app.token) return;
      showAttempt(r);
      $("pois-panel").hidden = false;
      $("pois-image").src = `/api/file?inline=1&name=${encodeURIComponent(r.image)}&t=${Date.now()}`;
      $("pois-message").textContent = r.message;
    } catch (err) {
      if (token === app.token) showAttempt(failedAttempt(err, "pois"));
    }
  }

  async function run() {
    const token = beginAttempt();
    $("run-status").textContent = "starting refflow track…";
    let r;
    try {
      r = await api("/api/run", request());
    } catch (err) {
      if (token === app.token) showAttempt(failedAttempt(err, "run"));
      return;
    }
    if (token !== app.token) return;
    showAttempt(r);
    setRunning(true);
    poll(token);
  }

  async function poll(token) {
    let status;
    try {
      status = await api("/api/run");
    } catch (err) {
      if (token !== app.token) return;
      say(err.message);
      setRunning(false);
      return;
    }
    if (token !== app.token) return;
    showAttempt(status);
    const progress = $("progress");
    progress.max = status.total || Math.max(status.done, 1);
    progress.value = status.done || 0;
    if (status.state === "running") {
      setTimeout(() => poll(token), 250);
      return;
    }
    setRunning(false);
    if (status.state === "done") {
      progress.value = progress.max;
      await showResult(status.name, token);
    } else {
      progress.value = 0;
    }
  }

  async function cancel() {
    try {
      await api("/api/cancel", {});
      $("run-status").textContent = `run #${app.attempt}: cancelling…`;
    } catch (err) {
      say(err.message);
    }
  }

  function fileLink(file, text) {
    const a = document.createElement("a");
    a.href = `/api/file?name=${encodeURIComponent(file)}`;
    a.download = file;
    a.textContent = text;
    a.className = "download";
    a.dataset.file = file;
    return a;
  }

  async function showResult(name, token) {
    let r;
    try {
      r = await api(`/api/result?name=${encodeURIComponent(name)}`);
    } catch (err) {
      if (token === app.token) say(err.message);
      return;
    }
    if (token !== app.token) return;
    app.result = r;
    $("results").hidden = false;
    const u = r.units;
    $("units-note").hidden = u !== "px";
    timePlot.set({
      title: `${r.label}: ${r.valid} of ${r.frames} frames valid`, x: "time (s)", y: `displacement (${u})`,
      series: [{name: `dx (${u})`, x: r.time_s, y: r.dx, color: COLOURS.dx},
               {name: `dy (${u})`, x: r.time_s, y: r.dy, color: COLOURS.dy}],
    });
    const series = [], markers = [];
    ["dx", "dy"].forEach((axis) => {
      const sp = r.spectra[axis];
      const peak = sp.peak_hz === null ? "" : `, peak ${sp.peak_hz.toFixed(3)} Hz`;
      series.push({name: `${axis}${peak}`, x: sp.freqs, y: sp.amplitude, color: COLOURS[axis]});
      if (sp.peak_hz !== null) markers.push({x: sp.peak_hz, label: `${sp.peak_hz.toFixed(3)} Hz`, color: COLOURS[axis]});
    });
    spectrumPlot.set({title: "amplitude spectrum", x: "frequency (Hz)", y: `amplitude (${u})`, series, markers,
                      home: r.view_hz ? {x0: 0, x1: r.view_hz} : null});
    const downloads = $("downloads");
    downloads.replaceChildren();
    const names = {csv: "CSV", sidecar: "sidecar JSON", project: "project JSON", mask: "mask PNG",
                   background: "background PNG"};
    for (const [role, text] of Object.entries(names)) {
      if (r.files[role]) downloads.append(fileLink(r.files[role], `↓ ${text}`));
    }
    $("results").dataset.ready = "1";
    $("results").scrollIntoView({behavior: "smooth", block: "nearest"});
  }

  // -- start ---------------------------------------------------------------------------------------

  async function start() {
    let info;
    try {
      info = await api("/api/info");
    } catch (err) {
      say(err.message);
      return;
    }
    app.info = info;
    document.title = `refflow: ${info.video_name}`;
    $("video-title").textContent = info.video_name;
    const fps = info.fps ? `, ${Number(info.fps.toFixed(3))} fps` : "";
    $("video-meta").textContent = `${info.width}×${info.height}, ${info.frames} frames${fps}` +
      (info.calibration ? ", calibrated" : "");
    $("frame-slider").max = String(Math.max(info.frames - 1, 0));
    $("run-name").value = info.name;
    $("out-dir").textContent = `files go to ${info.out_dir}`;
    const select = $("method");
    for (const m of info.methods) {
      const option = document.createElement("option");
      option.value = m.name;
      option.textContent = m.name;
      select.append(option);
    }
    select.value = info.default_method;
    if (info.project) load(info.project);
    methodChanged();
    updateScale();
    renderRegions();
    setTool("mask");
    resize();
    showFrame(0);
    if (info.notes.length) say(info.notes.join(" "), "info");
    // A page opened again (a reload) picks up the run in progress, or the last result.
    try {
      const status = await api("/api/run");
      if (status.attempt) {
        const token = beginAttempt();
        showAttempt(status);
        if (status.state === "running") { setRunning(true); poll(token); }
        else if (status.state === "done") await showResult(status.name, token);
      }
    } catch (err) {
      say(err.message);
    }
    app.ready = true;
    document.body.dataset.ready = "1";
  }

  document.querySelectorAll(".tool").forEach((b) => b.addEventListener("click", () => setTool(b.dataset.tool)));
  $("fit").addEventListener("click", fit);
  $("frame-slider").addEventListener("input", (e) => showFrame(Number(e.target.value)));
  $("roi").addEventListener("change", readRoiField);
  $("clear-roi").addEventListener("click", () => setRoi(null));
  $("known-length").addEventListener("input", updateScale);
  document.querySelectorAll("input[name=scale-mode]").forEach((r) => r.addEventListener("change", updateScale));
  $("mm-per-px").addEventListener("input", updateScale);
  $("mm-per-px").addEventListener("focus", () => { document.querySelector("input[value=mmpx]").checked = true; updateScale(); });
  $("known-length").addEventListener("focus", () => { document.querySelector("input[value=length]").checked = true; });
  $("method").addEventListener("change", methodChanged);
  $("use-frame").addEventListener("click", () => { $("reference-frame").value = String(app.shown); });
  $("save").addEventListener("click", save);
  $("show-pois").addEventListener("click", showPois);
  $("run").addEventListener("click", run);
  $("cancel").addEventListener("click", cancel);
  window.addEventListener("resize", resize);
  start();
})();
