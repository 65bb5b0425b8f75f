// kitti-eval pages: drag and drop onto the upload form, the size check, and the history's buttons.
// Without it the pages still work (the history's Compare sends ?e=&e= and the server orders the two),
// except the history's Open frame button.
"use strict";

function setupUpload() {
  const form = document.querySelector("form.upload");
  if (!form) return;
  const drop = document.getElementById("drop");
  const input = document.getElementById("predictions");
  const name = document.getElementById("drop-name");
  const note = document.getElementById("upload-note");
  const maxBytes = Number(form.dataset.maxBytes);

  const show = () => {
    const file = input.files && input.files[0];
    name.textContent = file ? `${file.name} (${(file.size / 1048576).toFixed(2)} MB)` : "";
    note.textContent = "";
  };
  input.addEventListener("change", show);
  for (const type of ["dragenter", "dragover"]) {
    drop.addEventListener(type, (event) => { event.preventDefault(); drop.classList.add("over"); });
  }
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (event) => {
    event.preventDefault();
    drop.classList.remove("over");
    if (event.dataTransfer && event.dataTransfer.files.length) {
      input.files = event.dataTransfer.files;
      show();
    }
  });
  form.addEventListener("submit", (event) => {
    const file = input.files && input.files[0];
    if (file && maxBytes && file.size > maxBytes) {
      event.preventDefault();
      note.textContent = `${file.name} is larger than the upload limit of ${(maxBytes / 1048576).toFixed(0)} MB.`;
      return;
    }
    const button = form.querySelector("button[type=submit]");
    button.disabled = true;
    button.textContent = "Evaluating…";
  });
}

function setupHistory() {
  const form = document.getElementById("history");
  if (!form) return;
  const compare = document.getElementById("compare");
  const openFrame = document.getElementById("open-frame");
  const frameId = document.getElementById("frame-id");
  const checked = () => Array.from(form.querySelectorAll("input[name=e]:checked"));

  const update = () => {
    const n = checked().length;
    compare.disabled = n !== 2;
    openFrame.disabled = n === 0 || !frameId.value.trim();
  };
  form.addEventListener("change", update);
  frameId.addEventListener("input", update);

  // the older of the two is the base: /compare?a=<older>&b=<newer>
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    const rows = checked().map((box) => box.closest("tr"));
    if (rows.length !== 2) return;
    rows.sort((x, y) => x.dataset.created.localeCompare(y.dataset.created));
    const query = new URLSearchParams({ a: rows[0].dataset.id, b: rows[1].dataset.id });
    window.location.href = `/compare?${query}`;
  });
  const goToFrame = () => {
    const frame = frameId.value.trim();
    const ids = checked().map((box) => box.value);
    if (!frame || !ids.length) return;
    const query = new URLSearchParams(ids.map((id) => ["e", id]));
    window.location.href = `/frames/${encodeURIComponent(frame)}?${query}`;
  };
  openFrame.addEventListener("click", goToFrame);
  frameId.addEventListener("keydown", (event) => {
    if (event.key === "Enter") { event.preventDefault(); goToFrame(); }
  });
  update();
}

document.addEventListener("DOMContentLoaded", () => {
  setupUpload();
  setupHistory();
});
