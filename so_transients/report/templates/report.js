// The events table of the vetting page: sort, filter, label, export the labels.
// Everything is in this folder: no request leaves it.
(function () {
  "use strict";
  var table = document.getElementById("events");
  var body = table.tBodies[0];
  var rows = Array.prototype.slice.call(body.rows);
  var meta = JSON.parse(document.getElementById("report-meta").textContent);
  var detections = JSON.parse(document.getElementById("detections").textContent);
  var storeKey = "so_transients_labels:" + meta.report_id;

  function loadLabels() {
    try { return JSON.parse(window.localStorage.getItem(storeKey) || "{}"); }
    catch (e) { return {}; }
  }
  function saveLabels(labels) {
    try { window.localStorage.setItem(storeKey, JSON.stringify(labels)); } catch (e) { /* file:// may refuse */ }
  }
  var labels = loadLabels();

  rows.forEach(function (row) {
    var select = row.querySelector("select.label");
    select.value = labels[row.dataset.uuid] || "";
    row.dataset.label = select.value;
    select.addEventListener("change", function () {
      labels[row.dataset.uuid] = select.value;
      if (!select.value) { delete labels[row.dataset.uuid]; }
      row.dataset.label = select.value;
      saveLabels(labels);
      applyFilters();
    });
    if (row.dataset.flags) { row.classList.add("flagged"); }
  });

  // sorting: a click on a header sorts by its column, a second click reverses
  var headers = Array.prototype.slice.call(table.tHead.rows[0].cells);
  headers.forEach(function (th) {
    th.addEventListener("click", function () {
      var key = th.dataset.key, numeric = th.dataset.type === "num";
      var asc = !th.classList.contains("sorted-asc");
      headers.forEach(function (h) { h.classList.remove("sorted-asc", "sorted-desc"); });
      th.classList.add(asc ? "sorted-asc" : "sorted-desc");
      rows.sort(function (a, b) {
        var x = a.dataset[key] || "", y = b.dataset[key] || "";
        var c;
        if (numeric) {
          var fx = parseFloat(x), fy = parseFloat(y);
          fx = isNaN(fx) ? Infinity : fx;   // not measured: last
          fy = isNaN(fy) ? Infinity : fy;
          c = fx - fy;
        } else {
          c = x.localeCompare(y);
        }
        return asc ? c : -c;
      });
      rows.forEach(function (r) { body.appendChild(r); });
    });
  });

  // filters
  var text = document.getElementById("filter-text");
  var snr = document.getElementById("filter-snr");
  var klass = document.getElementById("filter-class");
  var flagged = document.getElementById("filter-flagged");
  var label = document.getElementById("filter-label");
  function applyFilters() {
    var q = text.value.trim().toLowerCase();
    var minSnr = parseFloat(snr.value);
    var shown = 0;
    rows.forEach(function (r) {
      var haystack = [r.dataset.name, r.dataset.class, r.dataset.match, r.dataset.flags,
                      r.dataset.bands].join(" ").toLowerCase();
      var ok = (!q || haystack.indexOf(q) >= 0)
        && (isNaN(minSnr) || parseFloat(r.dataset.snr) >= minSnr)
        && (!klass.value || r.dataset.class === klass.value)
        && (!flagged.checked || r.dataset.flags)
        && (!label.value || (label.value === "none" ? !r.dataset.label
                                                    : r.dataset.label === label.value));
      r.style.display = ok ? "" : "none";
      if (ok) { shown += 1; }
    });
    document.getElementById("shown").textContent = shown + " of " + rows.length + " shown";
  }
  [text, snr, klass, flagged, label].forEach(function (el) {
    el.addEventListener("input", applyFilters);
    el.addEventListener("change", applyFilters);
  });
  applyFilters();

  // export: one CSV row per detection of each labelled event, with the score's inputs
  function csvValue(v) {
    var s = v === null || v === undefined ? "" : String(v);
    return /[",\n]/.test(s) ? '"' + s.replace(/"/g, '""') + '"' : s;
  }
  document.getElementById("export-labels").addEventListener("click", function () {
    var columns = ["event_uuid", "event_id", "label"].concat(meta.detection_columns);
    var lines = ["# so_transients vetting labels; report " + meta.report_id + "; events " + meta.source,
                 columns.join(",")];
    rows.forEach(function (r) {
      var value = labels[r.dataset.uuid];
      if (!value) { return; }
      (detections[r.dataset.uuid] || []).forEach(function (d) {
        lines.push([r.dataset.uuid, r.dataset.id, value].concat(
          meta.detection_columns.map(function (c) { return d[c]; })).map(csvValue).join(","));
      });
    });
    var blob = new Blob([lines.join("\n") + "\n"], {type: "text/csv"});
    var a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    a.download = "vetting_labels.csv";
    document.body.appendChild(a);
    a.click();
    setTimeout(function () { URL.revokeObjectURL(a.href); a.remove(); }, 0);
  });
}());
