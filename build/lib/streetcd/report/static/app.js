/* streetcd review page. Plain JavaScript, no framework, nothing fetched from outside.
 *
 * The data is window.STREETCD (data.js, written by `streetcd report` or served live by
 * `streetcd serve`). Coordinates are metres in the index's CRS; the map draws them in an SVG
 * whose user units are metres east and south of the extent's north-west corner (north up),
 * so the numbers the SVG holds stay small (float32 loses centimetres at UTM northings).
 */
(function () {
  "use strict";
  var D = window.STREETCD;
  var SVGNS = "http://www.w3.org/2000/svg";
  var STATUSES = ["confirmed", "false_alarm", "fixed"];
  var STATUS_KEYS = { c: "confirmed", f: "false_alarm", x: "fixed" };
  var state = { shown: [], cursor: -1, open: null, blink: false };
  var el = function (id) { return document.getElementById(id); };

  function make(tag, attrs, text) {
    var e = document.createElement(tag);
    Object.keys(attrs || {}).forEach(function (k) { e.setAttribute(k, attrs[k]); });
    if (text !== undefined && text !== null) e.textContent = String(text);
    return e;
  }

  // the store's words: a review's status, else "transient" (a car, a pedestrian), else "awaiting"
  function statusOf(c) {
    if (c.review && c.review.status) return c.review.status;
    return c.transient ? "transient" : "awaiting";
  }

  /* --- the night's numbers -------------------------------------------------------------- */
  function showNumbers() {
    var n = D.numbers, box = el("numbers");
    var run = n.run || {};
    var items = [
      ["views", n.views], ["done", n.done], ["flagged", n.flagged], ["failed", n.failed],
      ["changes", D.changes.length], ["segments", n.segments]
    ];
    items.forEach(function (it) {
      var s = make("span", { "class": "n", "data-n": it[0] });
      s.appendChild(make("b", {}, it[1]));
      s.appendChild(document.createTextNode(" " + it[0]));
      box.appendChild(s);
    });
    if (run.run_id) {
      box.appendChild(make("span", { "class": "n" },
        "run " + run.run_id + " (" + run.status + ", " + (run.started_at || "") + ")"));
    }
    if (n.failures && n.failures.length) {
      var det = make("details", { id: "failures" });
      det.appendChild(make("summary", {}, n.failed + " failed: why"));
      var ul = make("ul");
      n.failures.forEach(function (f) {
        ul.appendChild(make("li", {}, f.count + " × " + f.reason + " (e.g. " + f.views.join(", ") + ")"));
      });
      det.appendChild(ul);
      box.appendChild(det);
    }
    (D.notes || []).forEach(function (t) { box.appendChild(make("span", { "class": "n" }, "note: " + t)); });
  }

  /* --- filters and the list ------------------------------------------------------------- */
  function fillFilter(id, values, label) {
    var sel = el(id);
    values.forEach(function (v) { sel.appendChild(make("option", { value: v }, label ? label(v) : v)); });
    sel.addEventListener("change", applyFilters);
  }

  function unique(f) {
    var seen = {};
    D.changes.forEach(function (c) { seen[f(c)] = true; });
    return Object.keys(seen).filter(function (k) { return k !== "null"; }).sort();
  }

  function setupFilters() {
    fillFilter("f-segment", unique(function (c) { return c.segment; }));
    var names = {};
    D.changes.forEach(function (c) { names[c["class"]] = c.class_name; });
    fillFilter("f-class", unique(function (c) { return c["class"]; }), function (v) { return names[v] + " (" + v + ")"; });
    fillFilter("f-kind", unique(function (c) { return c.kind; }));
    fillFilter("f-status", ["awaiting", "transient"].concat(STATUSES));
  }

  function applyFilters() {
    var seg = el("f-segment").value, cls = el("f-class").value;
    var kind = el("f-kind").value, st = el("f-status").value;
    state.shown = D.changes.filter(function (c) {
      return (!seg || c.segment === seg) && (!cls || String(c["class"]) === cls) &&
        (!kind || c.kind === kind) && (!st || statusOf(c) === st);
    });
    state.cursor = state.shown.length ? 0 : -1;
    renderList();
    var ids = {};
    state.shown.forEach(function (c) { ids[c.id] = true; });
    Array.prototype.forEach.call(el("map").querySelectorAll("circle"), function (ci) {
      ci.classList.toggle("hidden", !ids[ci.getAttribute("data-id")]);
    });
  }

  function listItem(c, i) {
    var li = make("li", { "data-id": c.id, "data-i": i });
    li.appendChild(make("span", { "class": "conf" }, c.confidence.toFixed(2)));
    var mid = make("span");
    mid.appendChild(make("span", {}, c.class_name + " · " + c.kind));
    mid.appendChild(make("div", { "class": "meta" }, (c.segment || "no segment") + " · " + c.views.length + " view(s)"));
    li.appendChild(mid);
    li.appendChild(make("span", { "class": "status " + statusOf(c) }, statusOf(c).replace("_", " ")));
    li.addEventListener("click", function () { moveCursor(i); openChange(c); });
    return li;
  }

  function renderList() {
    var ol = el("list"), frag = document.createDocumentFragment();
    ol.textContent = "";
    state.shown.forEach(function (c, i) { frag.appendChild(listItem(c, i)); });
    ol.appendChild(frag);
    el("count").textContent = state.shown.length + " of " + D.changes.length + " changes";
    moveCursor(state.cursor);
  }

  function moveCursor(i) {
    var items = el("list").children;
    if (!items.length) { state.cursor = -1; return; }
    i = Math.max(0, Math.min(items.length - 1, i));
    if (items[state.cursor]) items[state.cursor].classList.remove("cursor");
    state.cursor = i;
    items[i].classList.add("cursor");
    if (items[i].scrollIntoView) items[i].scrollIntoView({ block: "nearest" });
  }

  /* --- the map -------------------------------------------------------------------------- */
  function extent() {
    var xs = [], ys = [];
    D.segments.forEach(function (s) { s.polyline.forEach(function (p) { xs.push(p[0]); ys.push(p[1]); }); });
    D.changes.forEach(function (c) { if (c.centroid.length) { xs.push(c.centroid[0]); ys.push(c.centroid[1]); } });
    if (!xs.length) return null;
    return { minx: Math.min.apply(null, xs), maxx: Math.max.apply(null, xs),
      miny: Math.min.apply(null, ys), maxy: Math.max.apply(null, ys) };
  }

  function drawMap() {
    var svg = el("map"), e = extent();
    if (!e) return;
    var w = Math.max(e.maxx - e.minx, 1), h = Math.max(e.maxy - e.miny, 1);
    var pad = 0.05 * Math.max(w, h);
    // user units: metres east of minx, metres south of maxy (SVG's y grows downwards)
    svg.setAttribute("viewBox", [-pad, -pad, w + 2 * pad, h + 2 * pad].join(" "));
    svg.setAttribute("data-origin", e.minx + " " + e.maxy);
    var X = function (x) { return x - e.minx; }, Y = function (y) { return e.maxy - y; };
    D.segments.forEach(function (s) {
      var pl = document.createElementNS(SVGNS, "polyline");
      pl.setAttribute("points", s.polyline.map(function (p) { return X(p[0]) + "," + Y(p[1]); }).join(" "));
      pl.setAttribute("data-segment", s.id);
      var t = document.createElementNS(SVGNS, "title");
      t.textContent = "segment " + s.id + " (" + s.n_views + " views, " + s.length_m + " m)";
      pl.appendChild(t);
      svg.appendChild(pl);
    });
    D.changes.forEach(function (c) {
      if (!c.centroid.length) return;
      var ci = document.createElementNS(SVGNS, "circle");
      ci.setAttribute("cx", X(c.centroid[0]));
      ci.setAttribute("cy", Y(c.centroid[1]));
      ci.setAttribute("class", c.kind);
      ci.setAttribute("data-id", c.id);
      var t = document.createElementNS(SVGNS, "title");
      t.textContent = c.class_name + " " + c.kind + " " + c.confidence.toFixed(2);
      ci.appendChild(t);
      ci.addEventListener("click", function () {
        var i = state.shown.indexOf(c);
        if (i >= 0) moveCursor(i);
        openChange(c);
      });
      svg.appendChild(ci);
    });
    sizeMarkers();
    window.addEventListener("resize", sizeMarkers);
  }

  // markers 9 px across whatever the map's scale (the SVG's units are metres)
  function sizeMarkers() {
    var svg = el("map"), m = svg.getScreenCTM();
    var r = 4.5 / (m && m.a ? m.a : 1);
    Array.prototype.forEach.call(svg.querySelectorAll("circle"), function (ci) { ci.setAttribute("r", r); });
  }

  /* --- one change ----------------------------------------------------------------------- */
  function pct(v) { return (100 * v).toFixed(2) + "%"; }

  function viewFigure(v) {
    var fig = make("figure", { "class": "view" });
    if (!v.thumb) {
      fig.appendChild(make("div", { "class": "missing" }, v.view + ": " + (v.note || "no picture")));
      return fig;
    }
    var box = make("div", { "class": "swipe" });
    var base = make("img", { src: v.old || v.thumb, alt: "old cloud from the pose of " + v.view });
    if (v.size) { base.setAttribute("width", v.size[0]); base.setAttribute("height", v.size[1]); }
    box.appendChild(base);
    var img = null;
    if (v.old) {
      img = make("img", { "class": "new", src: v.thumb, alt: v.view + " with the change outlined" });
      box.appendChild(img);
      box.appendChild(make("span", { "class": "tag l" }, "new"));
      box.appendChild(make("span", { "class": "tag r" }, "old cloud"));
    }
    if (v.box) {
      var b = make("div", { "class": "box" });
      b.style.left = pct(v.box[0]); b.style.top = pct(v.box[1]);
      b.style.width = pct(v.box[2] - v.box[0]); b.style.height = pct(v.box[3] - v.box[1]);
      box.appendChild(b);
    }
    fig.appendChild(box);
    if (img) {
      var slider = make("input", { type: "range", min: 0, max: 100, value: 50, "aria-label": "swipe new / old" });
      var set = function () { img.style.clipPath = "inset(0 " + (100 - slider.value) + "% 0 0)"; };
      slider.addEventListener("input", set);
      set();
      fig.appendChild(slider);
    }
    var cap = make("figcaption", {}, v.view + (v.sees_change ? "" : " (does not see the change)") + " ");
    if (v.full) cap.appendChild(make("a", { href: v.full, target: "_blank", rel: "noopener" }, "full image"));
    fig.appendChild(cap);
    return fig;
  }

  function openChange(c) {
    state.open = c;
    Array.prototype.forEach.call(el("list").children, function (li) {
      li.classList.toggle("open", li.getAttribute("data-id") === c.id);
    });
    Array.prototype.forEach.call(el("map").querySelectorAll("circle"), function (ci) {
      var mine = ci.getAttribute("data-id") === c.id;
      ci.classList.toggle("open", mine);
      if (mine) ci.parentNode.appendChild(ci);  // drawn last: on top of its neighbours
    });
    var d = el("detail");
    d.textContent = "";
    d.setAttribute("data-id", c.id);
    d.appendChild(make("h2", {}, c.class_name + " " + c.kind + " · confidence " + c.confidence.toFixed(2)));
    d.appendChild(make("p", {}, "id " + c.id + " · segment " + (c.segment || "-") + " · at " +
      c.centroid.map(function (x) { return x.toFixed(2); }).join(", ") + (D.crs ? " (" + D.crs + ")" : " (local frame)") +
      " · seen " + (c.first_seen || "?") + " → " + (c.last_seen || "?") + (c.transient ? " · transient: " + c.transient : "")));
    var rv = make("div", { "class": "review" });
    rv.appendChild(make("span", { "class": "status " + statusOf(c), id: "review-status" }, statusOf(c).replace("_", " ") +
      (c.review && c.review.who ? " by " + c.review.who : "") + (c.review && c.review.note ? ": " + c.review.note : "")));
    if (D.live) {
      var note = make("input", { type: "text", id: "review-note", placeholder: "note (optional)" });
      rv.appendChild(note);
      STATUSES.forEach(function (s) {
        var btn = make("button", { type: "button", "data-status": s }, s.replace("_", " "));
        btn.addEventListener("click", function () { decide(c, s); });
        rv.appendChild(btn);
      });
    }
    d.appendChild(rv);
    var views = make("div", { "class": "views" });
    c.views.forEach(function (v) { views.appendChild(viewFigure(v)); });
    d.appendChild(views);
    setBlink(state.blink);
  }

  function setBlink(on) {
    state.blink = on;
    Array.prototype.forEach.call(document.querySelectorAll(".swipe"), function (s) { s.classList.toggle("blink", on); });
  }

  /* --- decisions (live only) ------------------------------------------------------------ */
  function toast(text) {
    var t = el("toast");
    if (!t) { t = make("div", { id: "toast", role: "status" }); document.body.appendChild(t); }
    t.textContent = text; t.style.display = "block";
    clearTimeout(toast.timer);
    toast.timer = setTimeout(function () { t.style.display = "none"; }, 2500);
  }

  function decide(c, status) {
    var note = el("review-note");
    var token = new URLSearchParams(location.search).get("token") || "";
    var req = new XMLHttpRequest();
    req.open("POST", "api/review");
    req.setRequestHeader("Content-Type", "application/json");
    if (token) req.setRequestHeader("X-Streetcd-Token", token);
    req.onload = function () {
      if (req.status !== 200) { toast("not recorded: " + req.status + " " + req.responseText); return; }
      c.review = JSON.parse(req.responseText).review;
      var li = el("list").querySelector('li[data-id="' + CSS.escape(c.id) + '"]');
      if (li) li.replaceWith(listItem(c, Number(li.getAttribute("data-i"))));
      moveCursor(state.cursor);
      openChange(c);
      toast(c.id + ": " + status.replace("_", " ") + " recorded");
    };
    req.onerror = function () { toast("not recorded: the server did not answer"); };
    req.send(JSON.stringify({ id: c.id, status: status, note: note && note.value ? note.value : null }));
  }

  /* --- keys ----------------------------------------------------------------------------- */
  function onKey(ev) {
    var tag = (ev.target && ev.target.tagName) || "";
    if (tag === "INPUT" || tag === "SELECT" || tag === "TEXTAREA" || ev.ctrlKey || ev.metaKey || ev.altKey) return;
    var k = ev.key;
    if (k === "j" || k === "ArrowDown") { moveCursor(state.cursor + 1); }
    else if (k === "k" || k === "ArrowUp") { moveCursor(state.cursor - 1); }
    else if (k === "Enter") { if (state.shown[state.cursor]) openChange(state.shown[state.cursor]); }
    else if (k === "b") { setBlink(!state.blink); }
    else if (D.live && STATUS_KEYS[k] && state.open) { decide(state.open, STATUS_KEYS[k]); }
    else return;
    ev.preventDefault();
  }

  function main() {
    if (!D) { el("detail").textContent = "data.js is missing next to this page."; return; }
    document.title = D.title;
    el("title").textContent = D.title;
    document.body.classList.toggle("live", !!D.live);
    showNumbers();
    setupFilters();
    drawMap();
    applyFilters();
    document.addEventListener("keydown", onKey);
    document.body.setAttribute("data-ready", "1");
    if (window.performance && performance.mark) performance.mark("streetcd-ready");
  }

  main();
})();
