"use strict";
// The dashboard: live telemetry and previews (server-sent events), take controls, the take list.

const FAULT_WORDS = {
  trigger_silent: "The trigger box has gone quiet: check its USB cable and power.",
  trigger_garbage: "The trigger link sends garbage: check the cable and the baud rate.",
  device_failed: "A device failed and was written off for this take.",
  device_reconnecting: "A device was lost and is being reopened; its gap is recorded as a loss.",
  disk_low: "Disk space is below the reserve: no new take starts, a running one was stopped.",
  disk_full: "The disk is full: the take was stopped; free space, then run rigd recover.",
  queue_full: "The writer cannot keep up: data is being dropped (and counted).",
  overload: "More events than this host can write: whole time slices are shed at the source (counted, with their time range).",
  writer_failed: "The writer failed: the take is stopped.",
  writer_stalled: "The writer has not flushed for a while (slow or hung disk).",
};
const KIND_WORDS = { rgb_camera: "camera", event_sensor: "event sensor", trigger: "trigger" };
const tiles = {};
// A finished take's event rates do not change: fetched once, drawn again from here whenever the
// take list is rebuilt (during a take the rebuilt rows lost their curves while the fetch waited).
const rateCache = {};
let lastTakeSeen = null;
let lastState = null;

function tile(dev) {
  if (tiles[dev.name]) return tiles[dev.name];
  const img = el("img", { alt: dev.name, "data-testid": `img-${dev.name}` });
  const stats = el("div", { class: "stats" });
  const t = el("div", { class: "tile", "data-testid": `view-${dev.name}`, "data-version": "0" },
    el("div", { class: "name", text: `${dev.name} (${KIND_WORDS[dev.kind]})` }), img, stats);
  t._img = img; t._stats = stats; t._loading = false; t._want = 0;
  img.addEventListener("load", () => { t._loading = false; t.dataset.version = String(t._shown); });
  img.addEventListener("error", () => { t._loading = false; });
  document.getElementById("views").append(t);
  tiles[dev.name] = t;
  return t;
}

function showPreview(t, name, version) {
  // Latest value only: a browser still loading the previous image skips versions.
  if (t._loading || version === t._shown) return;
  t._loading = true; t._shown = version;
  loadImage(t._img, `/api/preview/${encodeURIComponent(name)}.jpg?v=${version}`).catch(() => { t._loading = false; });
}

// A camera delivering less than this share of the trigger rate during a take is losing frames.
const LOW_RATE_SHARE = 0.9;

function faultText(f) {
  // The fault's words, and its message only where it says more than them (no sentence twice).
  const words = FAULT_WORDS[f.code];
  if (!words) return f.message;
  const norm = (s) => s.toLowerCase().replace(/[^a-z0-9 ]/g, " ").split(/\s+/).filter((w) => w.length > 2);
  const known = new Set(norm(words));
  const extra = norm(f.message).filter((w) => !known.has(w) && !["being", "counted", "and"].includes(w));
  return extra.length ? `${words} (${f.message})` : words;
}

function deviceStats(dev, doc) {
  const residual = doc.last_take && doc.last_take.residual_rms_us ? doc.last_take.residual_rms_us[dev.name] : null;
  const unit = dev.kind === "event_sensor" ? "events" : dev.kind === "trigger" ? "pulses" : "frames";
  const parts = [
    `<b>${dev.state}</b>`,
    rateText(dev, doc),
    `${dev.total.toLocaleString()} ${unit}`,
    `lost <b>${dev.lost}</b>`,
  ];
  if (dev.shed) parts.push(`shed (overload) <b>${dev.shed.toLocaleString()}</b>`);
  if (dev.interval_jitter_us !== null && dev.interval_jitter_us !== undefined)
    parts.push(`trigger jitter <b>${dev.interval_jitter_us.toFixed(1)} µs</b>`);
  if (residual !== null && residual !== undefined) parts.push(`sync residual (last take) <b>${residual.toFixed(1)} µs</b>`);
  if (dev.last_data_age_s !== null && dev.last_data_age_s !== undefined) parts.push(`data age <b>${dev.last_data_age_s.toFixed(2)} s</b>`);
  if (dev.reconnects) parts.push(`reconnects <b>${dev.reconnects}</b>`);
  return parts.join(" · ");
}

function headroomText(doc) {
  // The writer's load, and the event rate against what this host's writer would hold.
  const busy = doc.writer_busy || 0;
  const events = doc.devices.filter((d) => d.kind === "event_sensor").reduce((a, d) => a + d.rate_hz, 0);
  let text = `writer ${(busy * 100).toFixed(0)} % busy (headroom ${(100 - busy * 100).toFixed(0)} %) · events ${(events / 1e6).toFixed(2)} Mev/s`;
  if (doc.event_capacity_hz) text += ` of ~${(doc.event_capacity_hz / 1e6).toFixed(0)} Mev/s this host holds`;
  const shed = doc.devices.reduce((a, d) => a + (d.shed || 0), 0);
  if (shed) text += ` · shed ${shed.toLocaleString()} events (overload)`;
  return text;
}

function rateText(dev, doc) {
  const trig = doc.devices.find((d) => d.kind === "trigger");
  const low = dev.kind === "rgb_camera" && doc.state === "capturing" && trig && trig.rate_hz > 0
    && dev.rate_hz < LOW_RATE_SHARE * trig.rate_hz;
  return low
    ? `rate <b class="low" data-testid="rate-low" title="below ${Math.round(LOW_RATE_SHARE * 100)} % of the trigger's ${trig.rate_hz.toFixed(1)} Hz: frames are being lost">${fmtRate(dev.rate_hz)}</b>`
    : `rate <b>${fmtRate(dev.rate_hz)}</b>`;
}

function render(doc) {
  const state = document.getElementById("state");
  state.textContent = doc.state;
  state.className = "pill " + (doc.faults.length ? "bad" : doc.state === "capturing" ? "ok" : doc.state === "idle" ? "" : "warn");
  document.getElementById("take-line").textContent = doc.take
    ? `take ${doc.take.split("/").pop()} · ${doc.take_elapsed_s.toFixed(1)} s · ${doc.pulses} pulses · queue ${doc.queue_depth}/${doc.queue_capacity} · ${fmtBytes(doc.bytes_written)} (${fmtBytes(doc.write_rate_bytes_s)}/s)`
    : `${doc.takes_completed} take(s) this run`;
  document.getElementById("headroom").textContent = doc.take ? headroomText(doc) : "";
  const trig = doc.devices.find((d) => d.kind === "trigger");
  document.getElementById("trigger").textContent = trig
    ? `trigger: ${trig.state === "idle" ? "idle" : trig.rate_hz.toFixed(1) + " Hz, " + trig.state}` : "";
  const freePct = doc.disk_total_bytes ? (100 * doc.disk_free_bytes / doc.disk_total_bytes).toFixed(0) : "?";
  document.getElementById("disk").textContent = `disk: ${fmtBytes(doc.disk_free_bytes)} free (${freePct} %)`;
  document.getElementById("flush").textContent = doc.last_flush_age_s === null || doc.last_flush_age_s === undefined
    ? "flush: -" : `flushed ${doc.last_flush_age_s.toFixed(1)} s ago: a crash now would lose the last ${doc.last_flush_age_s.toFixed(1)} s (longest flush ${(doc.flush_max_s * 1000).toFixed(0)} ms)`;
  const faults = document.getElementById("faults");
  faults.replaceChildren(...(doc.faults.length ? doc.faults.map((f) =>
    el("li", { text: `${f.device ? f.device + ": " : ""}${faultText(f)} (since ${f.since_utc})` }))
    : [el("li", { style: "color:var(--dim)", text: "none" })]));
  const hosts = doc.hosts || [];
  document.getElementById("hosts-section").hidden = !hosts.length;
  document.getElementById("hosts").replaceChildren(...hosts.map((h) =>
    el("li", { text: `host ${h.name} (${h.endpoint}): ${h.reachable ? h.state : "unreachable"} · ` +
      `${h.devices.join(", ") || "no devices"} · ${h.pulses} pulses${h.message ? " · " + h.message : ""}`,
      style: h.reachable && !h.message ? "" : "color:var(--bad)" })));
  for (const dev of doc.devices) {
    if (dev.kind === "trigger") continue;
    const t = tile(dev);
    t._stats.innerHTML = deviceStats(dev, doc);
    const v = (doc.previews || {})[dev.name];
    if (v) showPreview(t, dev.name, v);
  }
  document.getElementById("start").disabled = doc.state !== "idle";
  document.getElementById("stop").disabled = !(doc.state === "capturing" || doc.state === "starting");
  const lastPath = doc.last_take ? doc.last_take.path : null;
  if (lastPath !== lastTakeSeen || (lastState !== doc.state)) { lastTakeSeen = lastPath; lastState = doc.state; loadTakes(); }
}

function drawRates(canvas, series) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height;
  ctx.clearRect(0, 0, w, h);
  const ys = series.rate_hz;
  if (!ys.length) return;
  const max = Math.max(...ys, 1);
  const top = 13;  // the label's band: the curve is drawn below it, never under the text
  ctx.strokeStyle = "#58a6ff"; ctx.beginPath();
  ys.forEach((y, i) => { const x = i * w / Math.max(ys.length - 1, 1); const yy = h - 2 - (h - top - 2) * y / max; i ? ctx.lineTo(x, yy) : ctx.moveTo(x, yy); });
  ctx.stroke();
  ctx.fillStyle = "#9aa3ad"; ctx.font = "10px sans-serif"; ctx.fillText(fmtRate(max) + " max", 2, 10);
}

async function loadTakes() {
  const resp = await apiFetch("/api/takes");
  if (!resp.ok) return;
  const { takes } = await resp.json();
  const body = document.getElementById("takes");
  body.replaceChildren(...takes.map((t) => {
    const frames = Object.values(t.frames).reduce((a, b) => a + b, 0);
    const events = Object.values(t.events).reduce((a, b) => a + b, 0);
    const summary = t.status === "running" ? "recording now…"
      : `${t.status}${t.end_reason ? " (" + t.end_reason + ")" : ""}${t.recovered ? ", recovered" : ""}; ${frames.toLocaleString()} frames, ${events.toLocaleString()} events, ${t.pulses} pulses, ${fmtBytes(t.size_bytes)}, ${t.losses ? t.losses + " loss record(s)" : "nothing lost"}`;
    const info = el("td", {}, el("div", { text: summary }));
    if (t.verdict) {
      // The verdict: did the take keep everything (a degraded one is sealed but lost data).
      const cls = t.verdict === "complete" ? "ok" : t.verdict === "degraded" ? "warn" : "bad";
      const why = t.verdict_reasons.length ? " — " + t.verdict_reasons.join("; ") : "";
      info.prepend(el("div", { class: "verdict", "data-testid": "take-verdict" },
        el("span", { class: "pill " + cls, text: t.verdict }), el("span", { class: "msg", text: why })));
    }
    if (t.notes) info.append(el("div", { class: "msg", text: "notes: " + t.notes }));
    if (t.action) info.append(el("div", { class: "action", "data-testid": "take-action", text: t.action }));
    const thumbs = el("td", { class: "thumbs" });
    const rates = el("td", {});
    if (t.status === "complete") {
      for (const cam of t.cameras) {
        const im = el("img", { alt: cam, title: cam });
        thumbs.append(im);
        loadImage(im, `/api/takes/${encodeURIComponent(t.name)}/preview/${cam}.jpg`).catch(() => {});
      }
      const draw = (series) => {
        for (const [sensor, s] of Object.entries(series)) {
          const c = el("canvas", { class: "rate", width: "180", height: "44", title: sensor });
          rates.append(el("div", { text: sensor }), c); drawRates(c, s);
        }
      };
      if (rateCache[t.name]) draw(rateCache[t.name]);
      else apiFetch(`/api/takes/${encodeURIComponent(t.name)}/rates`)
        .then((r) => r.ok ? r.json() : null).then((series) => {
          if (series) { rateCache[t.name] = series; draw(series); }
        });
    }
    return el("tr", { "data-testid": "take-row", "data-name": t.name, "data-status": t.status },
      el("td", { text: t.name }), info, thumbs, rates);
  }));
}

function connect() {
  liveStream("/api/live", { status: (data) => render(JSON.parse(data)) },
    () => { document.getElementById("state").textContent = "reconnecting"; });
}

document.getElementById("take-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  const msg = document.getElementById("take-msg");
  const label = document.getElementById("label").value.trim();
  const dur = document.getElementById("duration").value.trim();
  const notes = document.getElementById("notes").value.trim();
  const body = { duration_s: dur ? Number(dur) : null };
  if (label) body.label = label;
  if (notes) body.notes = notes;
  msg.className = "msg"; msg.textContent = "opening the devices…";
  try {
    const r = await postJSON("/api/takes/start", body);
    msg.textContent = `recording ${r.result.take}`;
  } catch (err) { msg.className = "msg err"; msg.textContent = "not started: " + err.message; }
});

document.getElementById("stop").addEventListener("click", async () => {
  const msg = document.getElementById("take-msg");
  try {
    const r = await postJSON("/api/takes/stop", { reason: "stopped from the console" });
    msg.className = "msg"; msg.textContent = `stopping ${r.result.take}`;
  } catch (err) { msg.className = "msg err"; msg.textContent = "not stopped: " + err.message; }
});

document.getElementById("window").addEventListener("change", async (e) => {
  try { await postJSON("/api/event-window", { window_ms: Number(e.target.value) }); }
  catch (err) { document.getElementById("take-msg").textContent = err.message; }
});

connect();
loadTakes();
