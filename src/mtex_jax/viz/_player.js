// mtex view: a stick-figure motion player on a 2-D canvas with its own perspective camera
// (embedded inline by mtex_jax.viz.write_html; reads the JSON of <script id="mtex-data">).
(function () {
  "use strict";
  const errors = [];
  window.addEventListener("error", (e) => errors.push(String(e.message)));

  const DATA = JSON.parse(document.getElementById("mtex-data").textContent);
  // matplotlib's tab20, as in the PNG timelines of mtex_jax.viz.plot_timeline
  const PALETTE = [
    "#1f77b4", "#aec7e8", "#ff7f0e", "#ffbb78", "#2ca02c", "#98df8a", "#d62728", "#ff9896",
    "#9467bd", "#c5b0d5", "#8c564b", "#c49c94", "#e377c2", "#f7b6d2", "#7f7f7f", "#c7c7c7",
    "#bcbd22", "#dbdb8d", "#17becf", "#9edae5",
  ];
  const CONTACT = "#2ca02c";
  const FOV = (40 * Math.PI) / 180;
  const NEAR = 0.05;

  // ------------------------------------------------------------------------------------------
  // data
  // ------------------------------------------------------------------------------------------
  function bytesOf(b64) {
    const bin = atob(b64);
    const out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out;
  }

  function figure(f) {
    const raw = bytesOf(f.pos);
    const view = new DataView(raw.buffer);
    const n = raw.length / 2;
    const pts = new Float32Array(n);
    for (let i = 0; i < n; i++) pts[i] = f.origin[i % 3] + view.getInt16(2 * i, true) * f.unit;
    const contact = f.contact ? bytesOf(f.contact) : null;
    return Object.assign({}, f, { pts: pts, contact: contact });
  }

  function point(fig, t, k) {
    const i = (t * fig.P + k) * 3;
    return [fig.pts[i], fig.pts[i + 1], fig.pts[i + 2]];
  }

  function inContact(fig, t, j) {
    return fig.contact !== null && fig.contact[t * fig.feet.length + j] === 1;
  }

  function bounds(figs) {
    const lo = [Infinity, Infinity, Infinity];
    const hi = [-Infinity, -Infinity, -Infinity];
    for (const fig of figs) {
      for (let i = 0; i < fig.pts.length; i++) {
        const c = i % 3;
        if (fig.pts[i] < lo[c]) lo[c] = fig.pts[i];
        if (fig.pts[i] > hi[c]) hi[c] = fig.pts[i];
      }
    }
    return { lo: lo, hi: hi };
  }

  // ------------------------------------------------------------------------------------------
  // a view: one canvas, a camera orbiting a target, the floor and the figures
  // ------------------------------------------------------------------------------------------
  class View {
    constructor(canvas, figs, opts) {
      this.canvas = canvas;
      this.ctx = canvas.getContext("2d");
      this.figs = figs;
      this.labels = opts.labels;
      this.step = DATA.grid;
      this.size = DATA.size;
      const b = bounds(figs);
      const m = 0.3 * this.size;
      const s = this.step;
      this.floor = [
        Math.floor((b.lo[0] - m) / s) * s, Math.ceil((b.hi[0] + m) / s) * s,
        Math.floor((b.lo[1] - m) / s) * s, Math.ceil((b.hi[1] + m) / s) * s,
      ];
      this.box = b;
      this.az0 = opts.az;
      this.cam = null; // placed at the first draw, when the canvas has its size
      this.moved = false; // by the user
      this.dirty = true;
      if (opts.interactive) this.listen();
    }

    // the starting camera: the whole scene in view from the front, a little from above
    home() {
      const b = this.box;
      const aspect = this.canvas.width / Math.max(1, this.canvas.height);
      const tan = Math.tan(FOV / 2);
      const w = Math.max(b.hi[0] - b.lo[0], b.hi[1] - b.lo[1]) / 2 + 0.2 * this.size;
      const h = b.hi[2] / 2 + 0.15 * this.size;
      const depth = (b.hi[1] - b.lo[1]) / 2;
      return {
        az: this.az0, el: 0.3,
        dist: 1.1 * (Math.max(w / (tan * aspect), h / tan) + depth) + 0.5 * this.size,
        target: [(b.lo[0] + b.hi[0]) / 2, (b.lo[1] + b.hi[1]) / 2, 0.45 * b.hi[2]],
      };
    }

    listen() {
      const c = this.canvas;
      let drag = null;
      c.addEventListener("contextmenu", (e) => e.preventDefault());
      c.addEventListener("mousedown", (e) => {
        drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button !== 0 };
        e.preventDefault();
      });
      window.addEventListener("mouseup", () => (drag = null));
      window.addEventListener("mousemove", (e) => {
        if (!drag || !this.cam) return;
        const dx = e.clientX - drag.x;
        const dy = e.clientY - drag.y;
        drag.x = e.clientX;
        drag.y = e.clientY;
        this.moved = true;
        if (drag.pan) {
          const bs = this.basis();
          const k = this.cam.dist / bs.focal;
          for (let i = 0; i < 3; i++) this.cam.target[i] += (-dx * bs.r[i] + dy * bs.u[i]) * k;
        } else {
          this.cam.az -= dx * 0.008;
          this.cam.el = Math.min(1.5, Math.max(-0.05, this.cam.el + dy * 0.008));
        }
        this.dirty = true;
      });
      c.addEventListener("wheel", (e) => {
        e.preventDefault();
        if (!this.cam) return;
        const f = Math.exp(Math.max(-1, Math.min(1, e.deltaY * 0.0015)));
        this.cam.dist = Math.min(200 * this.size, Math.max(0.3 * this.size, this.cam.dist * f));
        this.moved = true;
        this.dirty = true;
      }, { passive: false });
      c.addEventListener("dblclick", () => {
        this.cam = this.home();
        this.moved = false;
        this.dirty = true;
      });
    }

    fit() {
      const dpr = window.devicePixelRatio || 1;
      const w = Math.max(1, Math.round(this.canvas.clientWidth * dpr));
      const h = Math.max(1, Math.round(this.canvas.clientHeight * dpr));
      if (this.canvas.width !== w || this.canvas.height !== h) {
        this.canvas.width = w;
        this.canvas.height = h;
        this.dirty = true;
        if (!this.moved) this.cam = null; // frame the scene again for the new shape
      }
      this.dpr = dpr;
    }

    basis() {
      const { az, el, dist, target } = this.cam;
      const dir = [Math.cos(el) * Math.cos(az), Math.cos(el) * Math.sin(az), Math.sin(el)];
      const eye = [0, 1, 2].map((i) => target[i] + dist * dir[i]);
      const f = dir.map((v) => -v);
      const rn = Math.hypot(f[1], f[0]) || 1;
      const r = [f[1] / rn, -f[0] / rn, 0]; // f × up, up = +z
      const u = [r[1] * f[2] - r[2] * f[1], r[2] * f[0] - r[0] * f[2], r[0] * f[1] - r[1] * f[0]];
      const focal = this.canvas.height / 2 / Math.tan(FOV / 2);
      return { eye, f, r, u, focal, cx: this.canvas.width / 2, cy: this.canvas.height / 2 };
    }

    toCam(p) {
      const bs = this.bs;
      const d = [p[0] - bs.eye[0], p[1] - bs.eye[1], p[2] - bs.eye[2]];
      return [
        d[0] * bs.r[0] + d[1] * bs.r[1] + d[2] * bs.r[2],
        d[0] * bs.u[0] + d[1] * bs.u[1] + d[2] * bs.u[2],
        d[0] * bs.f[0] + d[1] * bs.f[1] + d[2] * bs.f[2],
      ];
    }

    screen(c) {
      const s = this.bs.focal / c[2];
      return [this.bs.cx + c[0] * s, this.bs.cy - c[1] * s];
    }

    // screen position and depth of a world point, or null behind the near plane
    project(p) {
      const c = this.toCam(p);
      return c[2] < NEAR ? null : [...this.screen(c), c[2]];
    }

    // a world polygon clipped at the near plane, on screen
    polygon(pts) {
      const cam = pts.map((p) => this.toCam(p));
      const out = [];
      for (let i = 0; i < cam.length; i++) {
        const a = cam[i];
        const b = cam[(i + 1) % cam.length];
        if (a[2] >= NEAR) out.push(this.screen(a));
        if ((a[2] >= NEAR) !== (b[2] >= NEAR)) {
          const t = (NEAR - a[2]) / (b[2] - a[2]);
          out.push(this.screen([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), NEAR]));
        }
      }
      return out;
    }

    fillPolygon(pts, colour) {
      const s = this.polygon(pts);
      if (s.length < 3) return;
      const g = this.ctx;
      g.beginPath();
      g.moveTo(s[0][0], s[0][1]);
      for (const q of s.slice(1)) g.lineTo(q[0], q[1]);
      g.closePath();
      g.fillStyle = colour;
      g.fill();
    }

    line(p, q) {
      let a = this.toCam(p);
      let b = this.toCam(q);
      if (a[2] < NEAR && b[2] < NEAR) return;
      if (a[2] < NEAR || b[2] < NEAR) {
        if (a[2] < NEAR) [a, b] = [b, a];
        const t = (NEAR - a[2]) / (b[2] - a[2]);
        b = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), NEAR];
      }
      const s = this.screen(a);
      const e = this.screen(b);
      this.ctx.moveTo(s[0], s[1]);
      this.ctx.lineTo(e[0], e[1]);
    }

    disc(x, y, radius, colour) {
      const pts = [];
      for (let i = 0; i < 16; i++) {
        const a = (i * Math.PI) / 8;
        pts.push([x + radius * Math.cos(a), y + radius * Math.sin(a), 0]);
      }
      this.fillPolygon(pts, colour);
    }

    drawFloor() {
      const [x0, x1, y0, y1] = this.floor;
      this.fillPolygon([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], "#ececec");
      const g = this.ctx;
      const s = this.step;
      g.beginPath();
      for (let x = x0; x <= x1 + 1e-9; x += s) {
        for (let y = y0; y < y1 - 1e-9; y += s) this.line([x, y, 0], [x, y + s, 0]);
      }
      for (let y = y0; y <= y1 + 1e-9; y += s) {
        for (let x = x0; x < x1 - 1e-9; x += s) this.line([x, y, 0], [x + s, y, 0]);
      }
      g.strokeStyle = "#c2c2c2";
      g.lineWidth = this.dpr;
      g.stroke();
    }

    drawContacts(fig, t) {
      const r = 0.045 * this.size;
      const trail = Math.round(DATA.fps); // footprints of the last second
      for (let k = Math.max(0, t - trail); k <= t; k++) {
        for (let j = 0; j < fig.feet.length; j++) {
          if (!inContact(fig, k, j)) continue;
          const p = point(fig, k, fig.feet[j]);
          const now = k === t;
          const alpha = now ? 0.9 : 0.08 + 0.25 * (1 - (t - k) / trail);
          this.disc(p[0], p[1], now ? 1.6 * r : 0.6 * r, `rgba(44,160,44,${alpha.toFixed(3)})`);
        }
      }
    }

    // the figure's bones dropped onto the floor: how high it is, at a glance
    drawShadow(fig, t) {
      const g = this.ctx;
      g.beginPath();
      for (const [a, b] of fig.bones) {
        const p = point(fig, t, a);
        const q = point(fig, t, b);
        this.line([p[0], p[1], 0], [q[0], q[1], 0]);
      }
      g.strokeStyle = "rgba(0,0,0,0.13)";
      g.lineWidth = 3 * this.dpr;
      g.lineCap = "round";
      g.stroke();
    }

    draw(frames) {
      this.fit();
      if (!this.cam) this.cam = this.home();
      this.bs = this.basis();
      const g = this.ctx;
      g.setTransform(1, 0, 0, 1, 0, 0);
      g.fillStyle = "#ffffff";
      g.fillRect(0, 0, this.canvas.width, this.canvas.height);
      this.drawFloor();
      const items = [];
      this.figs.forEach((fig, i) => {
        const t = Math.min(frames[i], fig.n - 1);
        this.drawContacts(fig, t);
        this.drawShadow(fig, t);
        const pts = [];
        for (let k = 0; k < fig.P; k++) pts.push(this.project(point(fig, t, k)));
        const width = (z) => Math.max(1.2 * this.dpr, (0.024 * this.size * this.bs.focal) / z);
        fig.bones.forEach(([a, b], n) => {
          if (pts[a] && pts[b]) {
            const z = (pts[a][2] + pts[b][2]) / 2;
            items.push({ z, bone: [pts[a], pts[b]], colour: fig.colours[n], w: width(z) });
          }
        });
        const feet = new Map(fig.feet.map((k, j) => [k, inContact(fig, t, j)]));
        for (const k of fig.dots) {
          if (!pts[k]) continue;
          const c = feet.get(k) ? CONTACT : "#111111";
          items.push({ z: pts[k][2] - 1e-6, dot: pts[k], colour: c, w: width(pts[k][2]) });
        }
      });
      items.sort((a, b) => b.z - a.z);
      g.lineCap = "round";
      for (const it of items) {
        g.strokeStyle = it.colour;
        g.fillStyle = it.colour;
        if (it.bone) {
          g.lineWidth = it.w;
          g.beginPath();
          g.moveTo(it.bone[0][0], it.bone[0][1]);
          g.lineTo(it.bone[1][0], it.bone[1][1]);
          g.stroke();
        } else {
          g.beginPath();
          g.arc(it.dot[0], it.dot[1], 0.6 * it.w, 0, 2 * Math.PI);
          g.fill();
        }
      }
      if (this.labels) this.drawLabels(frames);
      this.dirty = false;
    }

    drawLabels(frames) {
      const g = this.ctx;
      g.font = `bold ${Math.round(14 * this.dpr)}px system-ui, sans-serif`;
      g.textAlign = "center";
      this.figs.forEach((fig, i) => {
        const t = Math.min(frames[i], fig.n - 1);
        let top = -Infinity;
        for (let k = 0; k < fig.P; k++) top = Math.max(top, point(fig, t, k)[2]);
        const root = point(fig, t, 0);
        const s = this.project([root[0], root[1], top + 0.15 * this.size]);
        if (!s) return;
        g.lineWidth = 4 * this.dpr;
        g.strokeStyle = "rgba(255,255,255,0.9)";
        g.strokeText(fig.label, s[0], s[1]);
        g.fillStyle = "#222";
        g.fillText(fig.label, s[0], s[1]);
      });
    }

    // for tests: per figure, where its highest point, its lowest foot and the floor below
    // that foot land on screen (y grows downwards), and the lowest foot's height
    check(frames) {
      this.fit();
      if (!this.cam) this.cam = this.home();
      this.bs = this.basis();
      return this.figs.map((fig, i) => {
        const t = Math.min(frames[i], fig.n - 1);
        let head = null;
        let foot = null;
        for (let k = 0; k < fig.P; k++) {
          const p = point(fig, t, k);
          if (!head || p[2] > head[2]) head = p;
        }
        for (const k of fig.feet) {
          const p = point(fig, t, k);
          if (!foot || p[2] < foot[2]) foot = p;
        }
        const sh = this.project(head);
        const sf = this.project(foot);
        const sg = this.project([foot[0], foot[1], 0]);
        return {
          label: fig.label, frame: t, headY: sh && sh[1], footY: sf && sf[1],
          floorY: sg && sg[1], footHeight: foot[2], width: this.canvas.width,
          height: this.canvas.height, footX: sf && sf[0],
        };
      });
    }
  }

  // ------------------------------------------------------------------------------------------
  // the page: the main player, its controls, the timelines and the gallery
  // ------------------------------------------------------------------------------------------
  const figs = DATA.motions.map(figure);
  const N = DATA.n_frames;
  const main = new View(document.getElementById("view"), figs, {
    labels: true, interactive: true, az: -Math.PI / 2 + 0.35,
  });
  const counter = document.getElementById("frame-counter");
  const slider = document.getElementById("slider");
  const playButton = document.getElementById("play");
  const speedBox = document.getElementById("speed");
  const tooltip = document.getElementById("tooltip");
  slider.max = String(N - 1);
  let frame = 0;
  let shown = -1;
  let playing = true;
  let speed = 1;
  let last = null;
  const playheads = [];

  function setPlaying(on) {
    playing = on;
    playButton.textContent = on ? "pause" : "play";
  }
  function seek(f) {
    frame = Math.max(0, Math.min(N - 1, Math.floor(f)));
    shown = -1;
  }
  playButton.addEventListener("click", () => setPlaying(!playing));
  slider.addEventListener("input", () => seek(Number(slider.value)));
  speedBox.addEventListener("change", () => (speed = Number(speedBox.value)));
  window.addEventListener("keydown", (e) => {
    if (e.code === "Space" && e.target === document.body) {
      e.preventDefault();
      setPlaying(!playing);
    }
  });

  function texText(lab) {
    const T = DATA.textons;
    const lines = [`texton ${lab}`];
    if (T) {
      lines.push(`training segments: ${T.count[lab]} · mean ${T.mean[lab].toFixed(2)} ${T.unit}`);
      const succ = T.succ[lab].map(([j, p]) => `${j} (${Math.round(100 * p)} %)`).join(", ");
      lines.push(`top successors: ${succ || "none"}`);
    }
    return lines;
  }

  function showTip(e, lines) {
    tooltip.textContent = lines.join("\n");
    tooltip.style.display = "block";
    tooltip.style.left = `${e.clientX + 12}px`;
    tooltip.style.top = `${e.clientY + 12}px`;
  }

  // timelines: one row per motion with a segmentation
  const rows = document.getElementById("timelines");
  figs.forEach((fig) => {
    if (!fig.timeline) return;
    const row = document.createElement("div");
    row.className = "timeline";
    const name = document.createElement("div");
    name.className = "name";
    name.textContent = fig.label;
    name.title = fig.label;
    const track = document.createElement("div");
    track.className = "track";
    for (const [start, len, lab] of fig.timeline) {
      const bar = document.createElement("div");
      bar.className = "seg";
      bar.style.left = `${(100 * start) / N}%`;
      bar.style.width = `${(100 * len) / N}%`;
      bar.style.background = PALETTE[lab % PALETTE.length];
      bar.textContent = String(lab);
      bar.dataset.start = String(start);
      bar.dataset.texton = String(lab);
      bar.addEventListener("click", () => seek(start));
      bar.addEventListener("mousemove", (e) => {
        const t0 = (start / DATA.fps).toFixed(2);
        const secs = `${t0}–${((start + len) / DATA.fps).toFixed(2)} s`;
        const lines = texText(lab);
        lines.splice(1, 0, `frames ${start}–${start + len - 1} (${secs})`);
        showTip(e, lines);
      });
      bar.addEventListener("mouseleave", () => (tooltip.style.display = "none"));
      track.appendChild(bar);
    }
    const head = document.createElement("div");
    head.className = "playhead";
    track.appendChild(head);
    playheads.push(head);
    row.append(name, track);
    rows.appendChild(row);
  });

  // gallery: one small looping player per texton
  const cards = [];
  let highlighted = null;
  function highlight(lab) {
    highlighted = highlighted === lab ? null : lab;
    for (const bar of document.querySelectorAll(".seg")) {
      const other = Number(bar.dataset.texton) !== highlighted;
      bar.classList.toggle("dim", highlighted !== null && other);
    }
  }
  if (DATA.gallery && DATA.gallery.length) {
    document.getElementById("gallery-title").hidden = false;
    const box = document.getElementById("gallery");
    const seen = new IntersectionObserver((entries) => {
      for (const e of entries) e.target.mtexVisible = e.isIntersecting;
    });
    for (const item of DATA.gallery) {
      const card = document.createElement("div");
      card.className = "card";
      card.style.borderColor = PALETTE[item.texton % PALETTE.length];
      const canvas = document.createElement("canvas");
      const cap = document.createElement("div");
      cap.className = "cap";
      const lines = texText(item.texton);
      const b = document.createElement("b");
      b.textContent = lines[0];
      cap.appendChild(b);
      for (const text of [...lines.slice(1), item.note]) {
        const div = document.createElement("div");
        div.textContent = text;
        cap.appendChild(div);
      }
      card.append(canvas, cap);
      card.title = "click: highlight this texton in the timelines";
      card.addEventListener("click", () => highlight(item.texton));
      box.appendChild(card);
      const view = new View(canvas, [figure(item.figure)], {
        labels: false, interactive: false, az: -Math.PI / 2 + 0.5,
      });
      cards.push({ card, view, shown: -1 });
      card.mtexVisible = false;
      seen.observe(card);
    }
  }

  function tick(ts) {
    if (last !== null && playing) {
      frame += ((ts - last) / 1000) * DATA.fps * speed;
      if (frame >= N) frame %= N;
    }
    last = ts;
    const f = Math.floor(frame);
    if (f !== shown || main.dirty) {
      main.draw(figs.map(() => f));
      shown = f;
      counter.textContent = `frame ${f} / ${N - 1} · ${(f / DATA.fps).toFixed(2)} s`;
      counter.dataset.frame = String(f);
      slider.value = String(f);
      for (const h of playheads) h.style.left = `${(100 * f) / N}%`;
    }
    for (const c of cards) {
      if (!c.card.mtexVisible) continue;
      const fig = c.view.figs[0];
      const g = Math.floor(((ts / 1000) * DATA.fps * speed) % fig.n);
      if (g !== c.shown || c.view.dirty) {
        c.view.draw([g]);
        c.shown = g;
      }
    }
    requestAnimationFrame(tick);
  }
  requestAnimationFrame(tick);

  // for tests and the curious: the player's state
  window.mtex = {
    nFrames: N,
    errors: errors,
    frame: () => Math.floor(frame),
    playing: () => playing,
    play: () => setPlaying(true),
    pause: () => setPlaying(false),
    seek: seek,
    check: () => main.check(figs.map(() => Math.floor(frame))),
  };
})();
