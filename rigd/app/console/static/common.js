"use strict";
// Shared helpers of the console pages: the token header for state-changing requests.
const RIGD_TOKEN = document.querySelector('meta[name="rigd-token"]').content;

async function postJSON(url, body) {
  const resp = await fetch(url, {
    method: "POST",
    headers: { "Content-Type": "application/json", "X-Rigd-Token": RIGD_TOKEN },
    body: JSON.stringify(body || {}),
    credentials: "same-origin",
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
