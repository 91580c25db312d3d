// TrafficRLHF annotation page: N candidate futures side by side, one clock for all canvases.
// Plain browser JavaScript, no build step. The server keeps all state (assignments, order, answers), so a
// reload resumes where the annotator was.
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const TOKEN_KEY = "trafficrlhf.token";
  const CAMPAIGN_KEY = "trafficrlhf.campaign";
  const TRAIL_S = 3.0;        // trail length behind each vehicle (s)
  const HOLD_S = 1.0;         // pause on the last frame before looping (s)
  const GUIDE_KEY = "trafficrlhf.guidelines.";  // + campaign: the guidelines version last acknowledged
  const COLOURS = { controlled: "#1f5fbf", vehicle: "#f28e2b", pedestrian: "#d62728", cyclist: "#2ca02c",
                    other: "#8c6d31", unset: "#7f7f7f" };
  const MIN_LENGTH_PX = 14;   // agents are drawn at least this long and wide on screen (CSS px)
  const MIN_WIDTH_PX = 7;
  const GAP_PX = 8;

  const state = {
    token: null, campaign: null, campaignInfo: null, item: null, frame: 0, clock: 0, playing: false, lastTick: null,
    speed: 1, loop: true, busy: false, shownAt: 0, cards: [], mapImage: null, played: true, overlay: false,
    whole: false, freshSignIn: false, guidelines: null,
    zoom: 1, panX: 0, panY: 0, drag: null, dragEnded: false,  // shared by every canvas, so zooming one zooms all
  };
  const ICON_PLAY = '<svg viewBox="0 0 16 16" width="14" height="14"><path d="M4 2v12l10-6z"/></svg>';
  const ICON_PAUSE = '<svg viewBox="0 0 16 16" width="14" height="14"><rect x="3" y="2" width="3.5" height="12"/><rect x="9.5" y="2" width="3.5" height="12"/></svg>';

  // ------------------------------------------------------------------------------------------ server
  async function api(method, path, body) {
    const headers = { Authorization: "Bearer " + state.token };
    if (body !== undefined) headers["Content-Type"] = "application/json";
    const res = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
    let data = null;
    try { data = await res.json(); } catch (_) { /* empty body */ }
    if (res.status === 401) { signOut((data && data.error) || "Please sign in again."); }
    if (!res.ok) {
      const err = new Error((data && data.error) || res.statusText || "request failed");
      err.status = res.status;
      throw err;
    }
    return data;
  }
  const campaignPath = () => "/api/campaigns/" + encodeURIComponent(state.campaign);

  // ------------------------------------------------------------------------------------------ screens
  function show(id) {
    for (const s of ["login", "picker", "guidelines", "done", "work"]) $(s).classList.toggle("hidden", s !== id);
  }

  function signOut(message) {
    localStorage.removeItem(TOKEN_KEY);
    state.token = null;
    state.item = null;
    $("login-error").textContent = message || "";
    show("login");
  }

  function toast(text, bad) {
    const el = $("toast");
    el.textContent = text;
    el.classList.toggle("bad", !!bad);
    el.classList.add("show");
    clearTimeout(toast.timer);
    toast.timer = setTimeout(() => el.classList.remove("show"), 1800);
  }

  function setProgress(p) {
    if (!p) return;
    const pct = p.total ? Math.round((100 * p.done) / p.total) : 0;
    $("progress-bar").style.width = pct + "%";
    $("progress-text").textContent = `${p.done} / ${p.total}` + (p.skipped ? ` (${p.skipped} skipped)` : "");
  }

  async function boot() {
    const params = new URLSearchParams(location.search);
    if (params.get("token")) state.freshSignIn = true;
    // keep the token out of the address bar and the history
    state.token = TrafficRLHFShared.takeTokenFromUrl(location, localStorage, TOKEN_KEY, history);
    if (!state.token) { show("login"); return; }
    let me;
    try { me = await api("GET", "/api/me"); } catch (err) { if (err.status !== 401) $("login-error").textContent = err.message; return; }
    $("annotator").textContent = me.annotator;
    const names = me.campaigns.map((c) => c.name);
    let chosen = params.get("campaign") || localStorage.getItem(CAMPAIGN_KEY) || me.default_campaign;
    if (!names.includes(chosen)) chosen = names.length === 1 ? names[0] : null;
    if (!chosen) {
      const list = $("campaign-list");
      list.innerHTML = "";
      for (const c of me.campaigns) {
        const li = document.createElement("li");
        const a = document.createElement("a");
        a.href = "?campaign=" + encodeURIComponent(c.name);
        a.textContent = `${c.name} — ${c.model}, ${c.progress.done} / ${c.progress.total} done`;
        li.appendChild(a);
        list.appendChild(li);
      }
      if (!names.length) list.textContent = "No campaign in this database yet.";
      show("picker");
      return;
    }
    state.campaign = chosen;
    state.campaignInfo = me.campaigns.find((c) => c.name === chosen);
    localStorage.setItem(CAMPAIGN_KEY, chosen);
    $("campaign-name").textContent = chosen;
    $("agreement-link").href = "/agreement?campaign=" + encodeURIComponent(chosen);
    const deepLink = Number(params.get("item"));  // ?item=ID opens that item (e.g. to discuss it)
    state.start = () => (deepLink > 0 ? loadItem(deepLink) : loadNext());
    await loadGuidelines();
    const version = state.campaignInfo.guidelines_version;
    $("guidelines-button").classList.toggle("hidden", !version);
    if (version && (state.freshSignIn || localStorage.getItem(GUIDE_KEY + chosen) !== version)) {
      $("guidelines-body").innerHTML = window.renderMarkdown(state.guidelines);
      show("guidelines");
      $("guidelines-ok").focus();
      return;
    }
    await state.start();
  }

  async function loadGuidelines() {
    state.guidelines = null;
    if (!state.campaignInfo.guidelines_version) return;
    const g = await api("GET", campaignPath() + "/guidelines");
    state.guidelines = g.markdown;
  }

  async function acknowledgeGuidelines() {
    localStorage.setItem(GUIDE_KEY + state.campaign, state.campaignInfo.guidelines_version);
    state.freshSignIn = false;
    await state.start();
  }

  function openGuidelines() {
    if (!state.guidelines) { toast("This campaign has no guidelines.", true); return; }
    play(false);
    $("guidelines-dialog-body").innerHTML = window.renderMarkdown(state.guidelines);
    $("guidelines-dialog").showModal();
  }

  async function loadNext() {
    const data = await api("GET", campaignPath() + "/next");
    setProgress(data.progress);
    if (data.done) {
      state.item = null; state.playing = false;
      const texts = {
        finished: ["All done — thank you!", "Every item of this campaign that needs you is labeled."],
        qualification_failed: ["Thank you", "Your answers on this campaign's check items did not reach the level it " +
          "needs, so no further items are assigned to you. Please contact the campaign owner."],
        qualification_unavailable: ["Please wait", "There is no check item for you right now; the campaign owner " +
          "has been asked to add some. Try again later."],
      };
      const [title, text] = texts[data.reason] || texts.finished;
      $("done-title").textContent = title;
      $("done-text").textContent = text;
      show("done");
      return;
    }
    showItem(data);
  }

  async function loadItem(id) {
    const data = await api("GET", campaignPath() + "/items/" + id);
    setProgress(data.progress);
    showItem(data);
  }

  // ------------------------------------------------------------------------------------------ item
  function showItem(item) {
    state.item = item;
    state.shownAt = performance.now();
    state.mapImage = null;
    if (item.map) {
      const img = new Image();
      img.onload = () => { if (state.item === item) { state.mapImage = img; draw(); } };
      img.src = item.map;
    }
    const n = item.candidates.length;
    $("key-n").textContent = String(n);
    $("hist-s").textContent = ((item.history_steps - 1) * item.dt).toFixed(1);
    $("scene-id").textContent = `item ${item.item} · position ${item.position}`;
    const grid = $("grid");
    state.zoom = 1; state.panX = 0; state.panY = 0; state.whole = false;
    grid.innerHTML = "";
    state.cards = item.candidates.map((cand) => {
      const card = document.createElement("div");
      card.className = "card";
      card.dataset.slot = cand.slot;
      card.title = `choose candidate ${cand.slot} (key ${cand.slot})`;
      const label = document.createElement("div");
      label.className = "label";
      label.textContent = cand.slot;
      const canvas = document.createElement("canvas");
      card.append(label, canvas);
      attachViewControls(card, canvas, cand.slot);
      grid.appendChild(card);
      return { card, canvas, cand };
    });
    const total = item.history_steps + item.future_steps;
    $("scrub").max = String(total - 1);
    markAnswer(item.status === "labeled" ? item.answer : null);
    const note = $("review-note");
    note.classList.toggle("hidden", item.status === "open");
    if (item.status === "labeled") {
      note.textContent = item.answer === 0 ? "You answered: none realistic — press a key to change it"
        : item.answer === "tie" ? "You answered: equally realistic — press a key to change it"
        : `You answered: ${item.answer} — press a key to change it`;
    } else if (item.status === "skipped") {
      note.textContent = `You skipped this item (${item.skip_reason}) — choose now to label it`;
    }
    $("forward").classList.toggle("hidden", item.status === "open");
    $("tie").classList.toggle("hidden", !item.allow_tie);
    $("tie-help").classList.toggle("hidden", !item.allow_tie);
    state.played = !item.playback_required || item.status !== "open";
    updateGate();
    show("work");
    resize();
    state.clock = 0;
    setFrame(0);
    play(true);
  }

  function updateGate() {
    const locked = !state.played;
    $("grid").classList.toggle("locked", locked);
    $("watch-note").classList.toggle("hidden", !locked);
    for (const b of document.querySelectorAll(".choice")) b.disabled = locked;
    updateWatchNote();
  }

  // the playback still needed before a choice counts, also while Space has paused the autoplay
  function playbackLeft() {
    return state.item ? TrafficRLHFShared.playbackLeft(state.clock, totalFrames(), state.item.dt) : 0;
  }

  function updateWatchNote() {
    if (state.played || !state.item) return;
    const text = TrafficRLHFShared.watchNote(playbackLeft(), state.playing);
    if ($("watch-note").textContent !== text) $("watch-note").textContent = text;
  }

  function markAnswer(slot) {
    for (const c of state.cards) c.card.classList.toggle("chosen", slot !== null && c.cand.slot === slot);
    $("none").classList.toggle("chosen", slot === 0);
    $("tie").classList.toggle("chosen", slot === "tie");
  }

  // ------------------------------------------------------------------------------------------ actions
  async function choose(slot) {
    const item = state.item;
    if (state.busy || !item) return;
    if (slot === "tie" ? !item.allow_tie : (slot < 0 || slot > item.candidates.length)) return;
    if (!state.played) {
      toast(`Watch the futures play through once before choosing: ${playbackLeft().toFixed(1)} s more.`, true);
      if (!state.playing) play(true);
      return;
    }
    state.busy = true;
    markAnswer(slot);
    const body = { choice: slot, time_ms: Math.round(performance.now() - state.shownAt) };
    const url = campaignPath() + "/items/" + item.item + "/label";
    try {
      if (item.status === "labeled") {
        await api("PUT", url, body);
        toast(`Changed to: ${describe(slot)}`);
      } else {
        await api("POST", url, body);
        toast(`Saved: ${describe(slot)}`);
      }
      await loadNext();
    } catch (err) {
      markAnswer(item.status === "labeled" ? item.answer : null);
      toast(err.message, true);
      if (err.status === 409) await loadItem(item.item).catch(() => {});
    } finally {
      state.busy = false;
    }
  }

  function describe(slot) { return slot === 0 ? "none realistic" : slot === "tie" ? "equally realistic" : String(slot); }

  function openSkip() {
    if (!state.item || state.busy) return;
    if (state.item.status === "labeled") { toast("Labeled items cannot be skipped; press a key to change the answer.", true); return; }
    play(false);
    $("skip-other").value = "";
    $("skip-dialog").showModal();
  }

  async function submitSkip() {
    const checked = document.querySelector("input[name=reason]:checked");
    let reason = checked ? checked.value : "other";
    if (reason === "other") reason = $("skip-other").value.trim() || "other";
    const item = state.item;
    state.busy = true;
    try {
      await api("POST", campaignPath() + "/items/" + item.item + "/skip", { reason });
      toast("Skipped");
      await loadNext();
    } catch (err) {
      toast(err.message, true);
    } finally {
      state.busy = false;
    }
  }

  async function back() {
    if (state.busy) return;
    const h = await api("GET", campaignPath() + "/history");
    const here = state.item ? state.item.position : Infinity;
    const earlier = h.items.filter((x) => x.position < here);
    if (!earlier.length) { toast("This is your first item.", true); return; }
    await loadItem(earlier[earlier.length - 1].item);
  }

  // ------------------------------------------------------------------------------------------ playback
  function totalFrames() { return state.item ? state.item.history_steps + state.item.future_steps : 1; }

  function play(on) {
    state.playing = on;
    state.lastTick = null;
    $("play").innerHTML = on ? ICON_PAUSE : ICON_PLAY;
    if (on && state.frame >= totalFrames() - 1) { state.clock = 0; setFrame(0); }
    updateWatchNote();
  }

  function setFrame(f) {
    const last = totalFrames() - 1;
    state.frame = Math.max(0, Math.min(last, f));
    draw();
  }

  function step(delta) {
    play(false);
    setFrame(state.frame + delta);
    state.clock = state.frame * state.item.dt;
    updateWatchNote();
  }

  function tick(ts) {
    if (state.playing && state.item) {
      if (state.lastTick !== null) state.clock += ((ts - state.lastTick) / 1000) * state.speed;
      state.lastTick = ts;
      const dt = state.item.dt;
      const last = totalFrames() - 1;
      let f = Math.floor(state.clock / dt + 1e-6);
      if (f >= last && !state.played) { state.played = true; updateGate(); }
      updateWatchNote();
      if (f > last) {
        if (!state.loop) { f = last; play(false); }
        else if (state.clock > last * dt + HOLD_S) { state.clock = 0; f = 0; }
        else f = last;
      }
      if (f !== state.frame) setFrame(f);
    }
    requestAnimationFrame(tick);
  }

  // ------------------------------------------------------------------------------------------ drawing
  function currentView() { return state.whole || !state.item.focus ? state.item.view : state.item.focus; }

  // the panels take all the room left under the header and above the controls: pick the number of columns
  // that gives the largest drawing scale for the current view
  function layout() {
    const item = state.item;
    if (!item || !state.cards.length) return;
    const grid = $("grid");
    const n = state.cards.length;
    const v = currentView();
    const vw = v.x1 - v.x0, vh = v.y1 - v.y0;
    const below = ["transport", "actions", "help"].map((c) => document.querySelector("#work ." + c))
      .reduce((sum, el) => sum + el.getBoundingClientRect().height + 10, 0);
    const availW = grid.clientWidth;
    const availH = Math.max(160, window.innerHeight - grid.getBoundingClientRect().top - below - 12);
    let best = null;
    for (let cols = 1; cols <= n; cols++) {
      const rows = Math.ceil(n / cols);
      const w = (availW - GAP_PX * (cols - 1)) / cols;
      const h = (availH - GAP_PX * (rows - 1)) / rows;
      const scale = Math.min(w / vw, h / vh);
      if (!best || scale > best.scale + 1e-9) best = { cols, w, h, scale };
    }
    const w = Math.floor(Math.min(best.w, best.scale * vw * 1.25));
    const h = Math.floor(Math.min(best.h, best.scale * vh * 1.25));
    grid.style.gridTemplateColumns = `repeat(${best.cols}, ${w}px)`;
    const dpr = window.devicePixelRatio || 1;
    for (const c of state.cards) {
      c.canvas.style.width = w + "px";
      c.canvas.style.height = h + "px";
      c.canvas.width = Math.max(1, Math.round(w * dpr));
      c.canvas.height = Math.max(1, Math.round(h * dpr));
    }
  }

  function resize() {
    layout();
    draw();
  }

  // state (x, y, yaw, valid) of agent a at frame f in candidate `cand`
  function agentAt(item, cand, a, f) {
    const H = item.history_steps;
    const src = f < H ? item.history : cand;
    const t = f < H ? f : f - H;
    return src.valid[a][t] ? [src.x[a][t], src.y[a][t], src.yaw[a][t]] : null;
  }

  function draw() {
    const item = state.item;
    if (!item) return;
    const f = state.frame;
    const H = item.history_steps;
    const t = (f - (H - 1)) * item.dt;
    $("clock").textContent = (t < 0 ? "t = " : "t = +") + t.toFixed(1) + " s" + (f < H - 1 ? " (past)" : f === H - 1 ? " (now)" : "");
    $("scrub").value = String(f);
    for (const c of state.cards) drawCanvas(c.canvas, item, c.cand, f);
  }

  function drawCanvas(canvas, item, cand, f) {
    const ctx = canvas.getContext("2d");
    const W = canvas.width, Hpx = canvas.height;
    const v = currentView(), whole = item.view;
    const s = Math.min(W / (v.x1 - v.x0), Hpx / (v.y1 - v.y0)) * state.zoom;
    const cx = (v.x0 + v.x1) / 2 + state.panX, cy = (v.y0 + v.y1) / 2 + state.panY;
    const X = (x) => W / 2 + (x - cx) * s;
    const Y = (y) => Hpx / 2 - (y - cy) * s;
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.fillStyle = "#f1efe8";
    ctx.fillRect(0, 0, W, Hpx);
    if (state.mapImage) {
      ctx.imageSmoothingEnabled = false;
      ctx.drawImage(state.mapImage, X(whole.x0), Y(whole.y1), (whole.x1 - whole.x0) * s, (whole.y1 - whole.y0) * s);
    }
    const trail = Math.round(TRAIL_S / item.dt);
    const dpr = window.devicePixelRatio || 1;
    if (state.overlay) drawOverlay(ctx, item, cand, X, Y, dpr);
    const boxes = [];
    item.agents.forEach((agent, a) => {
      if (!agent.present) return;
      const colour = agent.controlled ? COLOURS.controlled : (COLOURS[agent.type] || COLOURS.other);
      // trail: the last TRAIL_S seconds, fading out
      ctx.lineWidth = 2 * dpr;
      ctx.lineCap = "round";
      let prev = null;
      for (let g = Math.max(0, f - trail); g <= f; g++) {
        const p = agentAt(item, cand, a, g);
        if (p && prev) {
          ctx.strokeStyle = colour;
          ctx.globalAlpha = 0.15 + 0.65 * (1 - (f - g) / trail);
          ctx.beginPath();
          ctx.moveTo(X(prev[0]), Y(prev[1]));
          ctx.lineTo(X(p[0]), Y(p[1]));
          ctx.stroke();
        }
        prev = p;
      }
      ctx.globalAlpha = 1;
      const p = agentAt(item, cand, a, f);
      if (p) boxes.push([agent, colour, p]);
    });
    for (const [agent, colour, p] of boxes) {
      const [x, y, yaw] = p;
      const c = Math.cos(yaw), sn = Math.sin(yaw);
      const L = Math.max(agent.length, (MIN_LENGTH_PX * dpr) / s) / 2;  // never smaller than readable
      const Wd = Math.max(agent.width, (MIN_WIDTH_PX * dpr) / s) / 2;
      const pt = (lx, ly) => [X(x + c * lx - sn * ly), Y(y + sn * lx + c * ly)];
      const corners = [pt(L, Wd), pt(-L, Wd), pt(-L, -Wd), pt(L, -Wd)];
      ctx.beginPath();
      corners.forEach(([u, w], i) => (i ? ctx.lineTo(u, w) : ctx.moveTo(u, w)));
      ctx.closePath();
      ctx.fillStyle = colour;
      ctx.fill();
      ctx.lineWidth = 1 * dpr;
      ctx.strokeStyle = "#202020";
      ctx.stroke();
      const back = L - Math.min(0.8 * L, 1.6);  // heading: white triangle at the front
      const tri = [pt(L * 0.92, 0), pt(back, 0.6 * Wd), pt(back, -0.6 * Wd)];
      ctx.beginPath();
      tri.forEach(([u, w], i) => (i ? ctx.lineTo(u, w) : ctx.moveTo(u, w)));
      ctx.closePath();
      ctx.fillStyle = "rgba(255,255,255,0.92)";
      ctx.fill();
    }
    ctx.font = `${Math.round(11 * dpr)}px system-ui, "DejaVu Sans", sans-serif`;
    ctx.textAlign = "center";
    ctx.textBaseline = "bottom";
    for (const [agent, , p] of boxes) {  // labels last, above every box
      const r = Math.hypot(agent.length, agent.width) / 2;
      const text = agent.id.length > 8 ? agent.id.slice(0, 7) + "…" : agent.id;
      const u = X(p[0]), w = Y(p[1]) - r * s - 3 * dpr;
      const tw = ctx.measureText(text).width + 6 * dpr;
      ctx.fillStyle = "rgba(255,255,255,0.8)";
      ctx.fillRect(u - tw / 2, w - 13 * dpr, tw, 13 * dpr);
      ctx.fillStyle = "#1a1a1a";
      ctx.fillText(text, u, w);
    }
    if (f < item.history_steps) {  // the shared, recorded past
      ctx.font = `${Math.round(12 * dpr)}px system-ui, "DejaVu Sans", sans-serif`;
      ctx.textAlign = "right";
      ctx.textBaseline = "top";
      ctx.fillStyle = "rgba(90,90,90,0.9)";
      ctx.fillText(f === item.history_steps - 1 ? "now" : "recorded past", W - 8 * dpr, 8 * dpr);
    }
  }

  // every candidate's future path of the model's agents: this panel's solid, the others' dashed
  function drawOverlay(ctx, item, cand, X, Y, dpr) {
    const H = item.history_steps;
    const path = (src, a) => {
      ctx.beginPath();
      let pen = false;
      for (let t = 0; t < item.future_steps; t++) {
        if (!src.valid[a][t]) { pen = false; continue; }
        const u = X(src.x[a][t]), w = Y(src.y[a][t]);
        if (pen) ctx.lineTo(u, w); else { ctx.moveTo(u, w); pen = true; }
      }
      ctx.stroke();
    };
    item.agents.forEach((agent, a) => {
      if (!agent.controlled || !agent.present) return;
      ctx.lineWidth = 1.2 * dpr;
      ctx.setLineDash([4 * dpr, 3 * dpr]);
      ctx.strokeStyle = "rgba(60,60,60,0.55)";
      for (const other of item.candidates) if (other !== cand) path(other, a);
      ctx.setLineDash([]);
      ctx.lineWidth = 2.2 * dpr;
      ctx.strokeStyle = "rgba(31,95,191,0.75)";
      path(cand, a);
      const p = agentAt(item, cand, a, H - 1);
      if (p) { ctx.fillStyle = "#1f5fbf"; ctx.beginPath(); ctx.arc(X(p[0]), Y(p[1]), 2.5 * dpr, 0, 2 * Math.PI); ctx.fill(); }
    });
  }

  // wheel zooms about the cursor, drag pans (all canvases together); a click without a drag chooses the panel
  function resetView(whole) { state.zoom = 1; state.panX = 0; state.panY = 0; state.whole = !!whole; resize(); }

  function scaleOf(canvas) {
    const v = currentView(), rect = canvas.getBoundingClientRect();
    return [Math.min(rect.width / (v.x1 - v.x0), rect.height / (v.y1 - v.y0)), rect];
  }

  function attachViewControls(card, canvas, slot) {
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      const v = currentView();
      const [base, rect] = scaleOf(canvas);
      const u = e.clientX - rect.left - rect.width / 2, w = e.clientY - rect.top - rect.height / 2;
      const wx = (v.x0 + v.x1) / 2 + state.panX + u / (base * state.zoom);
      const wy = (v.y0 + v.y1) / 2 + state.panY - w / (base * state.zoom);
      state.zoom = Math.min(12, Math.max(0.5, state.zoom * Math.exp(-e.deltaY * 0.0015)));
      state.panX = wx - (v.x0 + v.x1) / 2 - u / (base * state.zoom);  // the point under the cursor stays put
      state.panY = wy - (v.y0 + v.y1) / 2 + w / (base * state.zoom);
      draw();
    }, { passive: false });
    canvas.addEventListener("mousedown", (e) => { state.drag = { canvas, card, x: e.clientX, y: e.clientY, moved: false }; });
    card.addEventListener("click", () => {
      if (state.dragEnded) { state.dragEnded = false; return; }
      choose(slot);
    });
  }

  window.addEventListener("mousemove", (e) => {
    const d = state.drag;
    if (!d || !state.item) return;
    const dx = e.clientX - d.x, dy = e.clientY - d.y;
    if (!d.moved && Math.hypot(dx, dy) < 4) return;
    d.moved = true;
    d.card.classList.add("dragging");
    const s = scaleOf(d.canvas)[0] * state.zoom;
    state.panX -= dx / s;
    state.panY += dy / s;
    d.x = e.clientX;
    d.y = e.clientY;
    draw();
  });
  window.addEventListener("mouseup", () => {
    const d = state.drag;
    state.drag = null;
    if (d && d.moved) { state.dragEnded = true; d.card.classList.remove("dragging"); setTimeout(() => { state.dragEnded = false; }, 0); }
  });

  // ------------------------------------------------------------------------------------------ wiring
  function toggleOverlay(on) {
    state.overlay = on;
    $("overlay").checked = on;
    $("overlay-legend").classList.toggle("hidden", !on);
    draw();
  }

  function toggleFullscreen() {
    if (document.fullscreenElement) document.exitFullscreen().catch(() => {});
    else document.documentElement.requestFullscreen().catch((err) => toast("Full screen refused: " + err.message, true));
  }

  function onKey(e) {
    if ($("skip-dialog").open || $("guidelines-dialog").open || e.ctrlKey || e.metaKey || e.altKey) return;
    if (e.target instanceof HTMLInputElement && e.target.type !== "range" && e.target.type !== "checkbox") return;
    if (!$("guidelines").classList.contains("hidden")) {
      if (e.key === "Enter") { e.preventDefault(); acknowledgeGuidelines().catch((err) => toast(err.message, true)); }
      return;
    }
    if ((e.key === "g" || e.key === "G") && state.guidelines) { openGuidelines(); e.preventDefault(); return; }
    if (!state.item || $("work").classList.contains("hidden")) {
      if ((e.key === "b" || e.key === "B") && !$("done").classList.contains("hidden")) { back(); e.preventDefault(); }
      return;
    }
    const n = state.item.candidates.length;
    let handled = true;
    if (/^[0-9]$/.test(e.key) && Number(e.key) <= n) choose(Number(e.key));
    else if ((e.key === "e" || e.key === "E") && state.item.allow_tie) choose("tie");
    else if (e.key === " ") play(!state.playing);
    else if (e.key === "ArrowLeft") step(e.shiftKey ? -Math.round(1 / state.item.dt) : -1);
    else if (e.key === "ArrowRight") step(e.shiftKey ? Math.round(1 / state.item.dt) : 1);
    else if (e.key === "Home") { state.clock = 0; setFrame(0); }
    else if (e.key === "z" || e.key === "Z") resetView(false);
    else if (e.key === "w" || e.key === "W") resetView(true);
    else if (e.key === "o" || e.key === "O") toggleOverlay(!state.overlay);
    else if (e.key === "f" || e.key === "F") toggleFullscreen();
    else if (e.key === "s" || e.key === "S") openSkip();
    else if (e.key === "b" || e.key === "B" || e.key === "Backspace") back().catch((err) => toast(err.message, true));
    else if ((e.key === "n" || e.key === "N" || e.key === "Enter") && state.item.status !== "open") loadNext();
    else handled = false;
    if (handled) e.preventDefault();
  }

  document.addEventListener("keydown", onKey);
  window.addEventListener("resize", resize);
  $("play").addEventListener("click", () => play(!state.playing));
  $("restart").addEventListener("click", () => { state.clock = 0; setFrame(0); });
  $("scrub").addEventListener("input", (e) => { play(false); setFrame(Number(e.target.value)); state.clock = state.frame * state.item.dt; });
  $("reset-view").addEventListener("click", () => resetView(false));
  $("whole-view").addEventListener("click", () => resetView(true));
  $("overlay").addEventListener("change", (e) => toggleOverlay(e.target.checked));
  $("fullscreen").addEventListener("click", toggleFullscreen);
  $("tie").addEventListener("click", () => choose("tie"));
  $("guidelines-ok").addEventListener("click", () => acknowledgeGuidelines().catch((err) => toast(err.message, true)));
  $("guidelines-button").addEventListener("click", openGuidelines);
  $("guidelines-close").addEventListener("click", () => $("guidelines-dialog").close());
  document.addEventListener("fullscreenchange", () => setTimeout(resize, 50));
  $("speed").addEventListener("change", (e) => { state.speed = Number(e.target.value); });
  $("loop").addEventListener("change", (e) => { state.loop = e.target.checked; });
  $("none").addEventListener("click", () => choose(0));
  $("skip").addEventListener("click", openSkip);
  $("back").addEventListener("click", () => back().catch((err) => toast(err.message, true)));
  $("forward").addEventListener("click", () => loadNext());
  $("done-back").addEventListener("click", () => back().catch((err) => toast(err.message, true)));
  $("logout").addEventListener("click", () => signOut(""));
  $("skip-cancel").addEventListener("click", () => $("skip-dialog").close("cancel"));
  $("skip-form").addEventListener("submit", () => { setTimeout(submitSkip, 0); });
  $("login-form").addEventListener("submit", (e) => {
    e.preventDefault();
    const t = $("token-input").value.trim();
    if (!t) return;
    localStorage.setItem(TOKEN_KEY, t);
    $("token-input").value = "";
    state.freshSignIn = true;
    boot().catch((err) => toast(err.message, true));
  });
  requestAnimationFrame(tick);
  boot().catch((err) => toast(err.message, true));
  window.trafficrlhf = state;  // for tests and debugging
})();
