"use strict";
// Shared helpers of the console pages. The console's secret is kept by this tab (sessionStorage,
// per origin: another port of 127.0.0.1 cannot read it) since the login URL put it there, and is
// sent as the X-Rigd-Token header on every request; no cookie carries it (cookies are sent to
// every port of a host). Images and the live stream are fetched with it too.
const RIGD_TOKEN = sessionStorage.getItem("rigd-token") || "";

if (!RIGD_TOKEN) {
  document.addEventListener("DOMContentLoaded", () => {
    document.body.prepend(el("p", { class: "msg err", "data-testid": "login-needed",
      text: "not logged in: open the login URL `rigd serve` printed (print it again with `rigd console-url`)" }));
  });
}

function apiFetch(url, opts) {
  const o = Object.assign({}, opts || {});
  o.headers = Object.assign({ "X-Rigd-Token": RIGD_TOKEN }, o.headers || {});
  o.credentials = "omit";
  return fetch(url, o);
}

// Show the image at `url` in `img` (fetched with the header, shown as a blob URL).
async function loadImage(img, url) {
  const resp = await apiFetch(url);
  if (!resp.ok) throw new Error(resp.statusText);
  const blob = await resp.blob();
  const old = img.src;
  img.src = URL.createObjectURL(blob);
  if (old && old.startsWith("blob:")) URL.revokeObjectURL(old);
}

// Save the file at `url` under `name` (fetched with the header).
async function downloadFile(url, name) {
  const resp = await apiFetch(url);
  if (!resp.ok) throw new Error(resp.statusText);
  const href = URL.createObjectURL(await resp.blob());
  const a = el("a", { href, download: name });
  document.body.append(a); a.click(); a.remove();
  setTimeout(() => URL.revokeObjectURL(href), 60000);
}

// Server-sent events read through fetch (EventSource cannot send the header): calls
// handlers[event](data) per event, onDown() when the stream breaks, and reconnects after 1 s.
function liveStream(url, handlers, onDown) {
  const run = async () => {
    try {
      const resp = await apiFetch(url, { headers: { Accept: "text/event-stream" } });
      if (!resp.ok || !resp.body) throw new Error(resp.statusText);
      const reader = resp.body.pipeThrough(new TextDecoderStream()).getReader();
      let buf = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buf += value;
        let cut;
        while ((cut = buf.indexOf("\n\n")) >= 0) {
          const block = buf.slice(0, cut); buf = buf.slice(cut + 2);
          let event = "message"; const data = [];
          for (const line of block.split("\n")) {
            if (line.startsWith("event:")) event = line.slice(6).trim();
            else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
          }
          if (data.length && handlers[event]) handlers[event](data.join("\n"));
        }
      }
    } catch (e) { /* reconnect below */ }
    if (onDown) onDown();
    setTimeout(run, 1000);
  };
  run();
}

async function postJSON(url, body) {
  const resp = await apiFetch(url, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(body || {}),
  });
  let doc = {};
  try { doc = await resp.json(); } catch (e) { doc = { ok: false, error: { message: resp.statusText } }; }
  if (!resp.ok || doc.ok === false) {
    const err = doc.error || {};
    throw new Error((err.message || resp.statusText) + (err.field ? ` (${err.field})` : ""));
  }
  return doc;
}

function fmtBytes(n) {
  if (n >= 1e9) return (n / 1e9).toFixed(1) + " GB";
  if (n >= 1e6) return (n / 1e6).toFixed(1) + " MB";
  if (n >= 1e3) return (n / 1e3).toFixed(0) + " kB";
  return n + " B";
}

function fmtRate(n) {
  if (n >= 1e6) return (n / 1e6).toFixed(2) + " M/s";
  if (n >= 1e3) return (n / 1e3).toFixed(1) + " k/s";
  return n.toFixed(1) + "/s";
}

function el(tag, attrs, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === "class") e.className = v; else if (k === "text") e.textContent = v; else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c);
  return e;
}
