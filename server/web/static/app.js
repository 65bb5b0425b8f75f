// kitti-eval pages: drag and drop onto the upload form, the size check, the history's buttons, and the
// benchmark submission's progress bar. Without it the pages still work (the history's Compare sends ?e=&e= and
// the server orders the two; a submission is sent by the form itself, without a bar), except the history's
// Open frame button and the Copy button of a token shown once (the token can still be selected by hand).
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

// A benchmark submission sent with XMLHttpRequest, to show its upload's progress. The answer is what the
// form would have got: a redirect to the submission's page (followed), or the benchmark's page again with why
// the file was refused (shown in place of this one).
function setupSubmission() {
  const form = document.querySelector("form.submission");
  if (!form || !window.XMLHttpRequest || !window.FormData || !window.DOMParser) return;
  const bar = document.getElementById("submit-progress");
  const note = document.getElementById("submit-note");
  const button = form.querySelector("button[type=submit]");
  const input = form.querySelector("input[type=file]");
  const maxBytes = Number(form.dataset.maxBytes);
  form.addEventListener("submit", (event) => {
    const file = input.files && input.files[0];
    if (!file) return;
    event.preventDefault();
    if (maxBytes && file.size > maxBytes) {
      note.textContent = `${file.name} is larger than the upload limit of ${(maxBytes / 1048576).toFixed(0)} MB.`;
      return;
    }
    const xhr = new XMLHttpRequest();
    xhr.open("POST", form.action);
    xhr.upload.addEventListener("progress", (e) => {
      if (!e.lengthComputable) return;
      bar.max = e.total;
      bar.value = e.loaded;
      note.textContent = `${Math.round((100 * e.loaded) / e.total)} % sent`;
    });
    xhr.upload.addEventListener("load", () => {
      bar.removeAttribute("value");  // indeterminate while the service checks the file
      note.textContent = "Sent; checking it…";
    });
    xhr.addEventListener("load", () => {
      if (xhr.status < 400 && xhr.responseURL && xhr.responseURL !== form.action) {
        window.location.assign(xhr.responseURL);
        return;
      }
      const page = new DOMParser().parseFromString(xhr.responseText, "text/html");
      document.title = page.title;
      document.body.replaceWith(document.adoptNode(page.body));
      setupSubmission();
    });
    xhr.addEventListener("error", () => {
      bar.hidden = true;
      button.disabled = false;
      note.textContent = "The upload stopped (the connection was lost); nothing was counted. Try again.";
    });
    bar.hidden = false;
    button.disabled = true;
    note.textContent = "0 % sent";
    xhr.send(new FormData(form));
  });
}

// A button with data-copy="ID" copies the text of the element ID (the token shown once after joining).
function setupCopy() {
  for (const button of document.querySelectorAll("button[data-copy]")) {
    const source = document.getElementById(button.dataset.copy);
    const note = document.getElementById("copy-note");
    button.addEventListener("click", async () => {
      const text = source.textContent.trim();
      let copied = false;
      try {
        await navigator.clipboard.writeText(text);
        copied = true;
      } catch (_) {
        const range = document.createRange();  // without the clipboard API (a page over plain HTTP): select it
        range.selectNodeContents(source);
        const selection = window.getSelection();
        selection.removeAllRanges();
        selection.addRange(range);
        copied = document.execCommand("copy");
      }
      if (note) note.textContent = copied ? "Copied." : "Selected: copy it with Ctrl+C.";
    });
  }
}

document.addEventListener("DOMContentLoaded", () => {
  setupCopy();
  setupUpload();
  setupHistory();
  setupSubmission();
});
