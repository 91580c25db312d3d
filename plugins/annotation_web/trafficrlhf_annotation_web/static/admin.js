// Campaign admin page: progress, annotators (add, deactivate, rotate tokens), agreement, gold items, settings
// and the export, all through /api/admin with the admin token (kept in this browser's local storage).
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const KEY = "trafficrlhf.admin";
  // `/admin?token=...` signs in as the annotator page's `?token=` does (the token leaves the address bar)
  const state = { token: TrafficRLHFShared.takeTokenFromUrl(location, localStorage, KEY, history), campaign: null,
                  data: null };
  const pct = (v) => (v === null || v === undefined ? "n/a" : (100 * v).toFixed(1) + " %");
  const num = (v, d = 3) => (v === null || v === undefined ? "n/a" : Number(v).toFixed(d));

  async function api(method, path, body, raw) {
    const headers = { Authorization: "Bearer " + state.token };
    if (body !== undefined) headers["Content-Type"] = "application/json";
    const res = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
    if (raw && res.ok) return res;
    const data = await res.json().catch(() => ({}));
    if (res.status === 401) { signOut(data.error); throw new Error(data.error || "sign in again"); }
    if (!res.ok) throw new Error(data.error || res.statusText);
    return data;
  }

  function signOut(message) {
    localStorage.removeItem(KEY);
    state.token = null;
    $("admin-error").textContent = message || "";
    $("admin-login").classList.remove("hidden");
    $("admin-main").classList.add("hidden");
  }

  function cell(tr, text, cls) { const td = document.createElement("td"); td.textContent = text; if (cls) td.className = cls; tr.appendChild(td); return td; }
  function stat(parent, value, label) {
    const div = document.createElement("div");
    div.innerHTML = '<div class="stat"></div><div class="muted"></div>';
    div.firstChild.textContent = value;
    div.lastChild.textContent = label;
    parent.appendChild(div);
  }

  async function boot() {
    if (!state.token) { signOut(""); return; }
    const overview = await api("GET", "/api/admin/overview");
    $("admin-name").textContent = overview.admin;
    $("admin-login").classList.add("hidden");
    $("admin-main").classList.remove("hidden");
    const select = $("campaign");
    select.innerHTML = "";
    for (const c of overview.campaigns) {
      const o = document.createElement("option");
      o.value = o.textContent = c.name;
      select.appendChild(o);
    }
    const wanted = new URLSearchParams(location.search).get("campaign") || overview.default_campaign;
    if (wanted && overview.campaigns.some((c) => c.name === wanted)) select.value = wanted;
    state.campaign = select.value;
    if (state.campaign) await refresh();
  }

  async function refresh() {
    const d = await api("GET", "/api/admin/campaigns/" + encodeURIComponent(state.campaign));
    state.data = d;
    const c = d.counts;
    const stats = $("stats");
    stats.innerHTML = "";
    stat(stats, c.items, `items (${d.models.join(", ")}, N = ${d.num_candidates})`);
    stat(stats, c.labels, `labels (${c.none_realistic} none, ${c.ties} ties)`);
    stat(stats, d.labels_per_item === null ? "all" : d.labels_per_item, "labels per item");
    stat(stats, d.labels_per_item === null ? "–" : `${c.items_complete} / ${c.items}`, "items complete");
    stat(stats, c.items_over_cap, "items over the cap");
    stat(stats, c.skips, "skips");
    stat(stats, c.gold_items, "gold items");
    const target = d.labels_per_item === null ? c.items * Math.max(1, d.annotators.filter((a) => a.active).length) : c.items * d.labels_per_item;
    const share = target ? Math.min(1, c.labels / target) : 0;
    $("campaign-bar").style.width = (100 * share).toFixed(1) + "%";
    $("campaign-bar-text").textContent = `${c.labels} of ${target} labels wanted (${pct(share)})`;
    const agreeBy = Object.fromEntries(d.agreement.annotators.map((a) => [a.annotator, a]));
    const body = $("annotators");
    body.innerHTML = "";
    for (const a of d.annotators) {
      const tr = document.createElement("tr");
      cell(tr, a.annotator + (a.active ? "" : " (inactive)"), a.active ? "" : "muted");
      for (const k of ["labels", "skips", "ties", "none_realistic", "open_items"]) cell(tr, a[k], "num");
      cell(tr, a.gold_answered ? `${a.gold_correct} / ${a.gold_answered} (${pct(a.gold_accuracy)})` : "–", "num");
      cell(tr, { none: "not asked", pending: "in progress", passed: "passed", failed: "failed" }[a.status],
           a.status === "failed" ? "bad" : a.status === "passed" ? "good" : "");
      cell(tr, pct(agreeBy[a.annotator] ? agreeBy[a.annotator].agree_with_majority : null), "num");
      cell(tr, a.median_time_ms === null ? "–" : (a.median_time_ms / 1000).toFixed(1) + " s", "num");
      const rotate = document.createElement("button");
      rotate.textContent = "new token";
      rotate.onclick = () => act(async () => showToken(a.annotator, (await api("POST", `/api/admin/annotators/${encodeURIComponent(a.annotator)}/token`)).token));
      cell(tr, "").appendChild(rotate);
      const toggle = document.createElement("button");
      toggle.textContent = a.active ? "deactivate" : "activate";
      toggle.onclick = () => act(() => api("PUT", `/api/admin/annotators/${encodeURIComponent(a.annotator)}/active`, { active: !a.active }));
      cell(tr, "").appendChild(toggle);
      const retake = cell(tr, "");
      if (a.status === "failed" || a.status === "passed") {  // the team lead lets them take the qualification again
        const button = document.createElement("button");
        button.textContent = "retake qualification";
        button.title = "Remove their answers to this campaign's gold items, so they qualify again from the start";
        button.onclick = () => act(() => api("POST", `/api/admin/campaigns/${encodeURIComponent(state.campaign)}/annotators/${encodeURIComponent(a.annotator)}/requalify`));
        retake.appendChild(button);
      }
      body.appendChild(tr);
    }
    const ag = d.agreement;
    const as = $("agreement-stats");
    as.innerHTML = "";
    stat(as, num(ag.fleiss_kappa), "Fleiss' κ");
    stat(as, pct(ag.pairwise_agreement), "pairwise agreement");
    stat(as, `${ag.items_multi} / ${ag.items}`, "items with ≥ 2 labels");
    const pairs = $("pairs");
    pairs.innerHTML = "";
    for (const p of ag.pairs) { const tr = document.createElement("tr"); cell(tr, p.a); cell(tr, p.b); cell(tr, p.shared, "num"); cell(tr, pct(p.agreement), "num"); pairs.appendChild(tr); }
    const s = d.settings;
    $("s-playback").checked = s.playback_required;
    $("s-tie").checked = s.allow_tie;
    $("s-gold-rate").value = s.gold_rate;
    $("s-qual").value = s.qualification_gold;
    $("s-qual-acc").value = s.qualification_accuracy;
    $("s-lease").value = s.lease_seconds;
    $("s-guidelines").value = s.guidelines || "";
  }

  function showToken(name, token) {
    const out = $("token-out");
    out.textContent = `${name}: ${token}  — give it to them now; it is not shown again. Link: ${location.origin}/?token=${token}`;
    out.classList.remove("hidden");
  }

  async function act(fn) {
    $("error").textContent = "";
    try { await fn(); await refresh(); } catch (err) { $("error").textContent = err.message; }
  }

  $("campaign").addEventListener("change", (e) => { state.campaign = e.target.value; act(async () => {}); });
  $("admin-logout").addEventListener("click", () => signOut(""));
  $("admin-login-form").addEventListener("submit", (e) => {
    e.preventDefault();
    state.token = $("admin-token").value.trim();
    localStorage.setItem(KEY, state.token);
    $("admin-token").value = "";
    boot().catch((err) => { $("admin-error").textContent = err.message; });
  });
  $("add-form").addEventListener("submit", (e) => {
    e.preventDefault();
    const name = $("new-name").value.trim();
    act(async () => { const r = await api("POST", "/api/admin/annotators", { name }); showToken(r.name, r.token); $("new-name").value = ""; });
  });
  $("settings-form").addEventListener("submit", (e) => {
    e.preventDefault();
    act(async () => {
      await api("PUT", `/api/admin/campaigns/${encodeURIComponent(state.campaign)}/settings`, {
        playback_required: $("s-playback").checked, allow_tie: $("s-tie").checked,
        gold_rate: Number($("s-gold-rate").value), qualification_gold: Number($("s-qual").value),
        qualification_accuracy: Number($("s-qual-acc").value), lease_seconds: Number($("s-lease").value),
        guidelines: $("s-guidelines").value });
      $("settings-out").textContent = "saved";
    });
  });
  $("gold-form").addEventListener("submit", (e) => {
    e.preventDefault();
    act(async () => {
      const r = await api("POST", `/api/admin/campaigns/${encodeURIComponent(state.campaign)}/gold`, { count: Number($("gold-count").value) });
      $("gold-out").textContent = `added ${r.added.length} gold items`;
    });
  });
  $("export-form").addEventListener("submit", (e) => {
    e.preventDefault();
    act(async () => {
      const q = new URLSearchParams({ ties: $("export-ties").value, val_fraction: $("export-val").value, only: $("export-only").value });
      const res = await api("GET", `/api/admin/campaigns/${encodeURIComponent(state.campaign)}/export?` + q, undefined, true);
      const blob = await res.blob();
      const a = document.createElement("a");
      a.href = URL.createObjectURL(blob);
      a.download = `${state.campaign}-preferences.zip`;
      document.body.appendChild(a);
      a.click();
      a.remove();
      $("export-out").textContent = `${res.headers.get("X-Pairs")} pairs from ${res.headers.get("X-Choices")} choices`;
    });
  });
  boot().catch((err) => { $("admin-error").textContent = err.message; signOut(err.message); });
  window.trafficrlhfAdmin = state;  // for tests
})();
