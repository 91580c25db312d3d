// "My figures": reads /api/campaigns/{name}/agreement (the signed-in annotator's own figures only).
"use strict";
(async () => {
  const $ = (id) => document.getElementById(id);
  const token = localStorage.getItem("trafficrlhf.token");
  const params = new URLSearchParams(location.search);
  const campaign = params.get("campaign") || localStorage.getItem("trafficrlhf.campaign");
  const pct = (v) => (v === null || v === undefined ? "n/a" : (100 * v).toFixed(1) + " %");
  if (!token || !campaign) { $("error").textContent = "Sign in on the labeling page first."; return; }
  $("campaign-name").textContent = campaign;
  $("back-link").href = "/?campaign=" + encodeURIComponent(campaign);
  const res = await fetch("/api/campaigns/" + encodeURIComponent(campaign) + "/agreement",
                          { headers: { Authorization: "Bearer " + token } });
  const data = await res.json().catch(() => ({}));
  if (!res.ok) { $("error").textContent = data.error || res.statusText; return; }
  const q = data.quality;
  $("done").textContent = `${data.progress.done} / ${data.progress.total}`;
  $("shared").textContent = data.annotator.shared;
  $("agree").textContent = pct(data.annotator.agree_with_majority);
  $("gold").textContent = q.gold_answered ? `${q.gold_correct} / ${q.gold_answered}` : "n/a";
  $("status").textContent = { none: "not needed", pending: "in progress", passed: "passed", failed: "not passed" }[q.status];
})();
