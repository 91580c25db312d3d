// Helpers the annotator page (app.js) and the admin page (admin.js) share, written as plain functions so that
// the tests can run them under node: the sign-in token taken from `?token=` and the play-once rule's countdown.
"use strict";
(function (root) {
  // A token in the address (`?token=...`) is stored under `key` and removed from the address bar and the
  // history; returns the stored token (from the address or from an earlier visit) or null.
  function takeTokenFromUrl(loc, storage, key, hist) {
    const params = new URLSearchParams(loc.search);
    const fromUrl = params.get("token");
    if (fromUrl) {
      storage.setItem(key, fromUrl);
      params.delete("token");
      const rest = params.toString();
      hist.replaceState(null, "", loc.pathname + (rest ? "?" + rest : ""));
    }
    return storage.getItem(key);
  }

  // Seconds of the futures still to play before a choice counts: the last frame is reached at
  // (frames - 1) * dt on the playback clock.
  function playbackLeft(clock, frames, dt) {
    return Math.max(0, (frames - 1) * dt - clock);
  }

  // The note under the panels while the choices are locked, playing or paused (Space pauses the autoplay).
  function watchNote(left, playing) {
    const s = left.toFixed(1);
    return playing
      ? `Watch ${s} s more: the choices unlock when the futures have played through.`
      : `Paused with ${s} s still to watch: press Space (or ▶) to play on; the choices unlock at the end.`;
  }

  const api = { takeTokenFromUrl, playbackLeft, watchNote };
  if (typeof module !== "undefined" && module.exports) module.exports = api;
  else root.TrafficRLHFShared = api;
})(this);
