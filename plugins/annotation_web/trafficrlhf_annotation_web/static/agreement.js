// Agreement page: reads /api/campaigns/{name}/agreement with the annotator's token.
"use strict";
(async () => {
  const $ = (id) => document.getElementById(id);
  const token = localStorage.getItem("trafficrlhf.token");
  const params = new URLSearchParams(location.search);
  const campaign = params.get("campaign") || localStorage.getItem("trafficrlhf.campaign");
  const fmt = (v, pct) => (v === null || v === undefined ? "n/a" : pct ? (100 * v).toFixed(1) + " %" : v.toFixed(3));
  if (!token || !campaign) { $("error").textContent = "Sign in on the labeling page first."; return; }
  $("campaign-name").textContent = campaign;
  $("back-link").href = "/?campaign=" + encodeURIComponent(campaign);
  const res = await fetch("/api/campaigns/" + encodeURIComponent(campaign) + "/agreement",
                          { headers: { Authorization: "Bearer " + token } });
  const data = await res.json().catch(() => ({}));
  if (!res.ok) { $("error").textContent = data.error || res.statusText; return; }
  $("kappa").textContent = fmt(data.fleiss_kappa);
  $("pairwise").textContent = fmt(data.pairwise_agreement, true);
  $("multi").textContent = `${data.items_multi} / ${data.items}`;
  $("labels").textContent = data.labels;
  $("none").textContent = data.none_realistic;
  $("skips").textContent = data.skips;
  const row = (cells) => { const tr = document.createElement("tr"); for (const c of cells) { const td = document.createElement("td"); td.textContent = c; tr.appendChild(td); } return tr; };
  for (const a of data.annotators) $("annotators").appendChild(row([a.annotator, a.labels, a.shared, fmt(a.agree_with_majority, true)]));
  for (const p of data.pairs) $("pairs").appendChild(row([p.a, p.b, p.shared, fmt(p.agreement, true)]));
})();
