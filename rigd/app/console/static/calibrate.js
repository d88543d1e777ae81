"use strict";
// Guided calibration page: pick a device and board, follow the live feedback, drop views, finish.

const ABBREV = { "facing": "F", "right-away": "R", "left-away": "L", "bottom-away": "B", "top-away": "T" };
let imgLoading = false, imgShown = 0, running = false;

// A result file: fetched with the header when clicked (a plain link would carry no secret).
function fileLink(kind, name) {
  const url = `/api/guided/files/${encodeURIComponent(name)}`;
  const a = el("a", { href: "#", "data-url": url, "data-testid": `guided-file-${kind}`, style: "margin-right:1em", text: `${kind}: ${name}` });
  a.addEventListener("click", (e) => {
    e.preventDefault();
    downloadFile(url, name).catch((err) => { document.getElementById("gmsg").textContent = err.message; });
  });
  return a;
}

async function loadDevices() {
  const r = await apiFetch("/api/guided");
  const info = await r.json();
  const sel = document.getElementById("gdevice");
  sel.replaceChildren(
    ...info.devices.cameras.map((c) => el("option", { value: c, text: `${c} (camera)` })),
    ...info.devices.event_sensors.map((s) => el("option", { value: s, text: `${s} (event sensor, frames reconstructed from its events)` })),
  );
  document.getElementById("gboard").value = info.devices.board;
  if (info.status) render(info.status);
  const tr = await apiFetch("/api/takes");
  if (tr.ok) {
    const { takes } = await tr.json();
    document.getElementById("gtake").append(...takes.filter((t) => t.status === "complete")
      .map((t) => el("option", { value: t.name, text: t.name })));
  }
}

function renderCoverage(doc) {
  const table = document.getElementById("gcov");
  const [cols, rows] = doc.grid;
  const fb = doc.feedback;
  const hintCell = fb.hint_cell;
  const trs = [];
  for (let r = 0; r < rows; r++) {
    const tds = [];
    for (let c = 0; c < cols; c++) {
      const counts = fb.coverage[r * cols + c];
      const n = counts.reduce((a, b) => a + b, 0);
      const seen = doc.tilt_bins.filter((t, i) => counts[i]).map((t) => ABBREV[t]).join("");
      const td = el("td", { text: n ? `${n} ${seen}` : "·" });
      td.style.background = n ? `rgba(63,185,80,${Math.min(0.15 + 0.2 * n, 0.8)})` : "";
      tds.push(td);
    }
    trs.push(el("tr", {}, ...tds));
  }
  table.replaceChildren(...trs);
  table.title = hintCell ? `next: ${hintCell}, ${fb.hint_tilt}` : "";
}

function render(doc) {
  const state = document.getElementById("gstate");
  state.textContent = doc.state;
  state.className = "pill " + ({ running: "ok", finished: doc.reached ? "ok" : "warn", failed: "bad" }[doc.state] || "");
  running = doc.state === "running";
  document.getElementById("gstart").disabled = running || doc.state === "finishing";
  document.getElementById("gfinish").disabled = !running;
  document.getElementById("gcancel").disabled = !running;
  const msg = document.getElementById("gmsg");
  if (doc.state === "failed") msg.textContent = doc.error;
  else if (!running && doc.state !== "finishing") msg.textContent = "";  // "calibrating cam0" ends with the session
  if (!running) document.getElementById("gleft").textContent = "";
  if (doc.image && doc.image !== imgShown && !imgLoading) {
    imgLoading = true; imgShown = doc.image;
    const img = document.getElementById("gimg");
    img.onload = () => {
      imgLoading = false; img.dataset.version = String(imgShown);
      img.hidden = false; document.getElementById("gnoimg").hidden = true;
    };
    img.onerror = () => { imgLoading = false; };
    loadImage(img, `/api/guided/image.jpg?v=${doc.image}`).catch(() => { imgLoading = false; });
  }
  if (running && doc.seconds_left !== undefined) document.getElementById("gleft").textContent = `${doc.seconds_left.toFixed(0)} s left`;
  if (doc.feedback) {
    const fb = doc.feedback;
    const still = fb.blur_px === null || fb.blur_px === undefined ? "" : `; smear ${fb.blur_px.toFixed(2)} px`;
    document.getElementById("greason").textContent =
      fb.detected ? `board found (${fb.n_corners} corners)${still}; ${fb.reason}` : fb.reason;
    document.getElementById("ghint").textContent = (fb.done ? "DONE: " : "next: ") + fb.next_hint;
    const row = document.getElementById("gsig");
    row.replaceChildren(el("td", { text: `std dev (target ${doc.target_sigma_px} px)` }), ...doc.sigma_names.map((n) => {
      const v = fb.sigmas[n];
      return el("td", { class: v === undefined ? "" : v <= doc.target_sigma_px ? "okv" : "high", text: v === undefined ? "-" : v.toFixed(3) });
    }));
    row.dataset.done = String(fb.done);
    renderCoverage(doc);
    document.getElementById("gviews").replaceChildren(...doc.views.map((v) => {
      const drop = el("button", { type: "button", class: "stop", "data-testid": "guided-drop", text: "drop" });
      drop.addEventListener("click", () => postJSON("/api/guided/drop", { index: v.index }).catch((e) => { document.getElementById("gmsg").textContent = e.message; }));
      return el("tr", { "data-testid": "guided-view" }, el("td", { text: String(v.index + 1) }), el("td", { text: v.cell }),
        el("td", { text: v.tilt }), el("td", { text: v.rms_px === null ? "-" : v.rms_px.toFixed(3) }), el("td", {}, drop));
    }));
  }
  if (doc.state === "finished") {
    const res = document.getElementById("gresult");
    const links = Object.entries(doc.files).map(([kind, name]) => kind === "take"
      ? el("span", { "data-testid": "guided-file-take", style: "margin-right:1em", text: `stored in take ${name}` })
      : fileLink(kind, name));
    const sig = Object.entries(doc.sigmas).map(([k, v]) => `${k} ${v.toFixed(3)}`).join(", ");
    const views = doc.views_text || `${doc.n_views} views`;
    // The report's warnings, as the report shows them: a result is judged by the same words here.
    const warnings = (doc.warnings || []).map((w) => el("li", { class: "action", "data-testid": "guided-warning", text: w }));
    res.replaceChildren(
      el("p", { class: doc.reached ? "hint" : "action", "data-testid": "guided-verdict", text: `${doc.camera}: ${doc.verdict}; ${views}${sig ? "; std dev (px) " + sig : ""}` }),
      ...(warnings.length ? [el("ul", { class: "warnings" }, ...warnings)] : []),
      el("p", { class: "files" }, ...links));
  }
}

document.getElementById("gform").addEventListener("submit", async (e) => {
  e.preventDefault();
  const msg = document.getElementById("gmsg");
  msg.textContent = "opening the camera…";
  document.getElementById("gresult").replaceChildren();
  try {
    const r = await postJSON("/api/guided/start", {
      camera: document.getElementById("gdevice").value,
      board: document.getElementById("gboard").value,
      target_sigma_px: Number(document.getElementById("gtarget").value),
      min_views: Number(document.getElementById("gmin").value),
    });
    msg.textContent = `calibrating ${r.result.camera} (${r.result.frame_size.join("x")})`;
  } catch (err) { msg.textContent = "not started: " + err.message; }
});
document.getElementById("gfinish").addEventListener("click", () => {
  const take = document.getElementById("gtake").value;
  postJSON("/api/guided/finish", { into_take: take || null }).catch((e) => { document.getElementById("gmsg").textContent = e.message; });
});
document.getElementById("gcancel").addEventListener("click", () => postJSON("/api/guided/cancel").catch((e) => { document.getElementById("gmsg").textContent = e.message; }));

liveStream("/api/live", { guided: (data) => render(JSON.parse(data)) });
loadDevices();
