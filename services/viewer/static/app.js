// RoadMap viewer: draws the map's tiles (PNGs in the paper's colours from /api/tile/TX/TY.png)
// in world metres (x east, y north), polls /api/state for tile versions and poses, pans
// (drag), zooms (wheel, +/-), and shows a clicked tile's version and its shard's stats.
// URL options: ?x=&y= (view centre, metres), &scale= (pixels per metre), &poll= (ms).
"use strict";
(function () {
  const canvas = document.getElementById("map");
  const ctx = canvas.getContext("2d");
  const params = new URLSearchParams(window.location.search);
  const num = (k) => (params.has(k) && params.get(k) !== "" ? Number(params.get(k)) : null);
  const POLL_MS = num("poll") || 500;
  const POSE_OK = "#30d158", POSE_BAD = "#ff9f0a", POSE_STALE = "#888888";

  const view = { x: num("x") ?? 0, y: num("y") ?? 0, scale: num("scale") ?? 4 };
  let fitted = num("x") !== null && num("y") !== null;
  const tiles = new Map(); // "tx,ty" -> {tx, ty, version, shard, img, shown}
  let poses = [], tileM = 51.2, selected = null, state = null, polls = 0;

  // -- coordinates ---------------------------------------------------------------------------
  function worldToScreen(x, y) {
    return [canvas.width / 2 + (x - view.x) * view.scale,
            canvas.height / 2 - (y - view.y) * view.scale];
  }
  function screenToWorld(px, py) {
    return [view.x + (px - canvas.width / 2) / view.scale,
            view.y - (py - canvas.height / 2) / view.scale];
  }

  // -- drawing -------------------------------------------------------------------------------
  function resize() {
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  }

  function draw() {
    resize();
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.fillStyle = "#000";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    ctx.imageSmoothingEnabled = false; // one map cell stays one crisp block
    const size = tileM * view.scale;
    for (const t of tiles.values()) {
      const [sx, sy] = worldToScreen(t.tx * tileM, (t.ty + 1) * tileM);
      if (sx > canvas.width || sy > canvas.height || sx + size < 0 || sy + size < 0) continue;
      if (t.img) ctx.drawImage(t.img, sx, sy, size, size);
      const isSel = selected && selected[0] === t.tx && selected[1] === t.ty;
      ctx.strokeStyle = isSel ? "rgba(90, 200, 250, 0.95)" : "rgba(90, 140, 220, 0.25)";
      ctx.lineWidth = isSel ? 2 : 1;
      ctx.strokeRect(Math.round(sx) + 0.5, Math.round(sy) + 0.5, Math.round(size), Math.round(size));
    }
    for (const p of poses) drawPose(p);
  }

  function drawPose(p) {
    const [px, py] = worldToScreen(p.x, p.y);
    const r = Math.max(7, Math.min(16, 2.2 * view.scale));
    const c = Math.cos(p.yaw), s = -Math.sin(p.yaw); // screen y points down
    ctx.fillStyle = p.stale ? POSE_STALE : (p.ok ? POSE_OK : POSE_BAD);
    ctx.strokeStyle = "#000";
    ctx.lineWidth = 1;
    ctx.beginPath();
    ctx.moveTo(px + 1.6 * r * c, py + 1.6 * r * s);
    ctx.lineTo(px - r * c - 0.9 * r * s, py - r * s + 0.9 * r * c);
    ctx.lineTo(px - r * c + 0.9 * r * s, py - r * s - 0.9 * r * c);
    ctx.closePath();
    ctx.fill();
    ctx.stroke();
    ctx.font = "12px system-ui, sans-serif";
    ctx.fillStyle = "#fff";
    ctx.fillText(p.vehicle, px + 1.8 * r, py - 1.2 * r);
  }

  // -- data ----------------------------------------------------------------------------------
  function apply(s) {
    state = s;
    tileM = s.tile_m;
    poses = s.poses;
    for (const t of s.tiles) {
      const key = t.tx + "," + t.ty;
      let e = tiles.get(key);
      if (!e) { e = { tx: t.tx, ty: t.ty, img: null, shown: null, loading: null }; tiles.set(key, e); }
      e.version = t.version;
      e.shard = t.shard;
      if (e.shown !== t.version && e.loading !== t.version) loadTile(e, t.version);
    }
    if (!fitted && tiles.size) { fit(); fitted = true; }
    legend(s.classes);
    summary(s);
    vehicles(s.poses);
    draw();
  }

  function loadTile(e, version) {
    e.loading = version;
    const img = new Image();
    img.onload = () => {
      if (e.shown === null || version > e.shown) { e.img = img; e.shown = version; }
      draw();
    };
    img.onerror = () => { e.loading = null; };
    img.src = "/api/tile/" + e.tx + "/" + e.ty + ".png?v=" + version;
  }

  async function poll() {
    try {
      const r = await fetch("/api/state", { cache: "no-store" });
      if (!r.ok) throw new Error(r.status);
      apply(await r.json());
      polls += 1;
    } catch (err) {
      document.getElementById("summary").textContent = "viewer server not answering";
    } finally {
      setTimeout(poll, POLL_MS);
    }
  }

  // -- panel ---------------------------------------------------------------------------------
  let legendDone = false;
  function legend(classes) {
    if (legendDone || !classes) return;
    const ul = document.getElementById("legend");
    for (const c of classes) {
      const li = document.createElement("li");
      const sw = document.createElement("span");
      sw.className = "swatch";
      sw.style.background = "rgb(" + c.rgb.join(",") + ")";
      li.append(sw, document.createTextNode(c.name.replace("_", " ")));
      ul.append(li);
    }
    legendDone = true;
  }

  function summary(s) {
    const shards = Object.keys(s.shards).length;
    const alive = s.alive || {};
    const n = (k) => (alive[k] || []).length;
    document.getElementById("summary").innerHTML =
      "<div>" + s.tiles.length + " tiles &middot; " + shards + " shards &middot; " +
      s.poses.length + " poses</div><div class='muted'>" + n("vehicle") + " vehicles, " +
      n("localizer") + " localizers alive &middot; " + esc(s.source) + "</div>";
  }

  function vehicles(list) {
    const ul = document.getElementById("vehicles");
    ul.textContent = "";
    if (!list.length) { ul.innerHTML = "<li class='muted'>no poses yet</li>"; return; }
    for (const p of list) {
      const li = document.createElement("li");
      li.className = p.stale ? "muted" : (p.ok ? "ok" : "warn");
      li.textContent = p.vehicle + "  x " + p.x.toFixed(1) + "  y " + p.y.toFixed(1) +
        "  \u03c3 " + p.sigma_m.toFixed(2) + " m" + (p.stale ? " (stale)" : "");
      ul.append(li);
    }
  }

  async function selectTile(tx, ty) {
    selected = [tx, ty];
    draw();
    const info = document.getElementById("info");
    try {
      const r = await fetch("/api/tile/" + tx + "/" + ty, { cache: "no-store" });
      if (r.status === 404) { info.innerHTML = "<span class='muted'>no tile " + tx + ", " + ty + "</span>"; return; }
      const d = await r.json();
      const rows = [["tile", d.tile.join(", ")], ["version", d.version], ["codec", d.codec],
                    ["bytes", d.bytes], ["shard", d.shard || "?"], ["updated", d.received_s_ago + " s ago"]];
      for (const [k, v] of Object.entries(d.shard_stats || {})) rows.push([k, v]);
      info.innerHTML = "<table>" + rows.map(([k, v]) => {
        const text = String(v), short = text.length > 20 ? text.slice(0, 16) + "\u2026" : text;
        return "<tr><td>" + esc(String(k)) + "</td><td title='" + esc(text) + "'>" + esc(short) +
          "</td></tr>";
      }).join("") + "</table>";
      info.dataset.tile = d.tile.join(",");
      info.dataset.version = d.version;
    } catch (err) {
      info.textContent = "could not read tile " + tx + ", " + ty;
    }
  }

  function esc(s) {
    return s.replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", "\"": "&quot;", "'": "&#39;" }[c]));
  }

  // -- interaction ---------------------------------------------------------------------------
  function fit() {
    if (!tiles.size) return;
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    for (const t of tiles.values()) {
      x0 = Math.min(x0, t.tx * tileM); y0 = Math.min(y0, t.ty * tileM);
      x1 = Math.max(x1, (t.tx + 1) * tileM); y1 = Math.max(y1, (t.ty + 1) * tileM);
    }
    resize();
    view.x = (x0 + x1) / 2;
    view.y = (y0 + y1) / 2;
    view.scale = Math.min(canvas.width / (x1 - x0), canvas.height / (y1 - y0)) * 0.9;
    draw();
  }

  function zoomAt(factor, px, py) {
    const [wx, wy] = screenToWorld(px, py);
    view.scale = Math.max(0.05, Math.min(200, view.scale * factor));
    const [nx, ny] = screenToWorld(px, py);
    view.x += wx - nx;
    view.y += wy - ny;
    draw();
  }

  let drag = null;
  canvas.addEventListener("pointerdown", (ev) => {
    drag = { x: ev.clientX, y: ev.clientY, vx: view.x, vy: view.y, moved: false };
    canvas.setPointerCapture(ev.pointerId);
  });
  canvas.addEventListener("pointermove", (ev) => {
    const [wx, wy] = screenToWorld(ev.offsetX, ev.offsetY);
    document.getElementById("cursor").textContent =
      "x " + wx.toFixed(1) + " m  y " + wy.toFixed(1) + " m  tile " +
      Math.floor(wx / tileM) + ", " + Math.floor(wy / tileM);
    if (!drag) return;
    const dx = ev.clientX - drag.x, dy = ev.clientY - drag.y;
    if (Math.abs(dx) + Math.abs(dy) > 3) { drag.moved = true; canvas.classList.add("dragging"); }
    view.x = drag.vx - dx / view.scale;
    view.y = drag.vy + dy / view.scale;
    draw();
  });
  canvas.addEventListener("pointerup", (ev) => {
    canvas.classList.remove("dragging");
    if (drag && !drag.moved) {
      const [wx, wy] = screenToWorld(ev.offsetX, ev.offsetY);
      selectTile(Math.floor(wx / tileM), Math.floor(wy / tileM));
    }
    drag = null;
  });
  canvas.addEventListener("wheel", (ev) => {
    ev.preventDefault();
    zoomAt(Math.exp(-ev.deltaY * 0.0015), ev.offsetX, ev.offsetY);
  }, { passive: false });
  document.getElementById("zoom-in").onclick = () => zoomAt(1.5, canvas.width / 2, canvas.height / 2);
  document.getElementById("zoom-out").onclick = () => zoomAt(1 / 1.5, canvas.width / 2, canvas.height / 2);
  document.getElementById("fit").onclick = fit;
  window.addEventListener("resize", draw);

  // for scripts and tests: what the page holds and shows
  window.roadmapViewer = {
    view, worldToScreen, screenToWorld, selectTile, fit,
    polls: () => polls,
    shown: () => Object.fromEntries([...tiles.entries()].map(([k, t]) => [k, t.shown])),
    poses: () => poses.map((p) => p.vehicle),
  };
  poll();
})();
