// The report's 3D view (rigbuild/report/viewer.py packs the data): a rig with one slider per shape, and
// playback of each retargeted take on its character. Vertices are blended on the CPU,
// v = neutral + sum_k w_k delta_k over each shape's sparse deltas, and drawn with three.js (global THREE).
// Errors of the page go to #rb-errors (errors.js); with ?selfcheck (or #selfcheck) in the URL the page moves one slider and one take
// frame itself and writes what moved to #rb-selfcheck (the report's Chromium test reads both).
(function () {
  "use strict";
  var errors = window.rbErrors || [];
  var note = window.rbNote || function (msg) { errors.push(String(msg)); };

  function bytes(b64) {
    var s = atob(b64), out = new Uint8Array(s.length);
    for (var i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
    return out.buffer;
  }
  function typed(b64, Type) { return new Type(bytes(b64)); }

  var inline = document.getElementById("rb-viewer-data");
  var data = window.RB_VIEWER_DATA || JSON.parse(inline.textContent);  // report_files/viewer-data.js, or inline
  var topo = {};
  var models = {};

  function faces(key, n) {
    if (!topo[key]) topo[key] = typed(data.topologies[key], n <= 65535 ? Uint16Array : Uint32Array);
    return topo[key];
  }
  function model(id) {
    if (models[id]) return models[id];
    var m = data.models[id], V = m.n_vertices;
    var q = typed(m.neutral.q, Int16Array), neutral = new Float32Array(3 * V);
    for (var i = 0; i < V; i++)
      for (var c = 0; c < 3; c++) neutral[3 * i + c] = m.neutral.lo[c] + (q[3 * i + c] + 32767) * m.neutral.step[c];
    var idx = typed(m.idx, V <= 65535 ? Uint16Array : Uint32Array), dq = typed(m.deltas, Int16Array);
    var shapes = [], at = 0;
    for (var k = 0; k < m.shapes.length; k++) {
      var n = m.counts[k], d = new Float32Array(3 * n);
      for (var j = 0; j < 3 * n; j++) d[j] = dq[3 * at + j] * m.scales[k];
      shapes.push({ name: m.shapes[k], idx: idx.subarray(at, at + n), d: d });
      at += n;
    }
    var index = {};
    m.shapes.forEach(function (s, k) { index[s] = k; });
    models[id] = { id: id, label: m.label, V: V, neutral: neutral, faces: faces(m.faces, V), shapes: shapes,
                   index: index, weights: new Float32Array(m.shapes.length) };
    return models[id];
  }
  function blend(mdl, pos) {
    pos.set(mdl.neutral);
    for (var k = 0; k < mdl.shapes.length; k++) {
      var w = mdl.weights[k];
      if (w === 0) continue;
      var s = mdl.shapes[k], idx = s.idx, d = s.d;
      for (var i = 0; i < idx.length; i++) {
        var v = 3 * idx[i];
        pos[v] += w * d[3 * i]; pos[v + 1] += w * d[3 * i + 1]; pos[v + 2] += w * d[3 * i + 2];
      }
    }
  }

  // ---------------------------------------------------------------- three.js scene (when WebGL exists)
  var box = document.getElementById("rb-canvas");
  var probe = document.createElement("canvas");
  var gl = !!(window.WebGLRenderingContext && (probe.getContext("webgl2") || probe.getContext("webgl")));
  var renderer = null, scene, camera, group, mesh, positions, current = null, dirty = true;
  var yaw = 0, pitch = 0, dist = 1;
  if (gl && window.THREE) {
    renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    renderer.setPixelRatio(window.devicePixelRatio || 1);
    box.appendChild(renderer.domElement);
    scene = new THREE.Scene();
    scene.background = new THREE.Color(0xf4f4f4);
    camera = new THREE.PerspectiveCamera(30, 1, 1, 100000);
    scene.add(new THREE.HemisphereLight(0xffffff, 0x777788, 0.75));
    var key = new THREE.DirectionalLight(0xffffff, 0.6);
    key.position.set(0.5, 0.7, 1);
    scene.add(key);
    group = new THREE.Group();
    scene.add(group);
  } else {
    var p = document.createElement("p");
    p.className = "hint";
    p.textContent = "3D view needs WebGL; the sliders and playback still compute the mesh.";
    box.appendChild(p);
  }
  function resize() {
    if (!renderer) return;
    var w = box.clientWidth || 640, h = box.clientHeight || 480;
    renderer.setSize(w, h);
    camera.aspect = w / h;
    camera.updateProjectionMatrix();
    dirty = true;
  }
  function show(mdl) {
    current = mdl;
    positions = new Float32Array(3 * mdl.V);
    blend(mdl, positions);
    if (!renderer) return;
    if (mesh) { group.remove(mesh); mesh.geometry.dispose(); mesh.material.dispose(); }
    var g = new THREE.BufferGeometry();
    g.setAttribute("position", new THREE.BufferAttribute(positions, 3));
    g.setIndex(new THREE.BufferAttribute(mdl.faces, 1));
    g.computeVertexNormals();
    g.computeBoundingSphere();
    mesh = new THREE.Mesh(g, new THREE.MeshStandardMaterial({ color: 0xd8b49c, roughness: 0.7, metalness: 0,
                                                              side: THREE.DoubleSide }));
    var c = g.boundingSphere.center;
    mesh.position.set(-c.x, -c.y, -c.z);
    group.add(mesh);
    dist = g.boundingSphere.radius * 4.2;
    resize();
  }
  function update() {
    if (!current) return;
    blend(current, positions);
    if (mesh) {
      mesh.geometry.attributes.position.needsUpdate = true;
      mesh.geometry.computeVertexNormals();
    }
    dirty = true;
  }
  function render() {
    group.rotation.set(pitch, yaw, 0);
    camera.position.set(0, 0, dist);
    camera.lookAt(0, 0, 0);
    renderer.render(scene, camera);
  }
  function draw() {
    if (renderer && dirty && mesh) {
      render();
      dirty = false;
    }
    requestAnimationFrame(draw);
  }
  if (renderer) {
    var drag = null;
    renderer.domElement.addEventListener("pointerdown", function (e) { drag = [e.clientX, e.clientY]; });
    window.addEventListener("pointerup", function () { drag = null; });
    window.addEventListener("pointermove", function (e) {
      if (!drag) return;
      yaw += (e.clientX - drag[0]) * 0.01;
      pitch = Math.max(-1.5, Math.min(1.5, pitch + (e.clientY - drag[1]) * 0.01));
      drag = [e.clientX, e.clientY];
      dirty = true;
    });
    renderer.domElement.addEventListener("wheel", function (e) {
      e.preventDefault();
      dist *= Math.exp(e.deltaY * 0.001);
      dirty = true;
    }, { passive: false });
    window.addEventListener("resize", resize);
  }

  // ---------------------------------------------------------------- controls: sliders, takes, playback
  var select = document.getElementById("rb-select"), sliderBox = document.getElementById("rb-sliders");
  var frame = document.getElementById("rb-frame"), frameText = document.getElementById("rb-frametext");
  var playBtn = document.getElementById("rb-playbtn"), playRow = document.getElementById("rb-play");
  var sliders = [], take = null, takeW = null, playing = false, t0 = 0, f0 = 0;
  Object.keys(data.models).forEach(function (id) {
    if (id !== "m0" && data.takes.length) return;  // characters appear through their takes
    var o = document.createElement("option");
    o.value = "model:" + id; o.textContent = data.models[id].label;
    select.appendChild(o);
  });
  data.takes.forEach(function (t, i) {
    var o = document.createElement("option");
    o.value = "take:" + i; o.textContent = "take " + t.label;
    select.appendChild(o);
  });
  function buildSliders(mdl) {
    sliderBox.textContent = "";
    sliders = mdl.shapes.map(function (s, k) {
      var row = document.createElement("label"), input = document.createElement("input"), out = document.createElement("span");
      input.type = "range"; input.min = "0"; input.max = "1"; input.step = "0.01"; input.value = mdl.weights[k];
      input.setAttribute("data-shape", s.name);
      out.textContent = Number(mdl.weights[k]).toFixed(2);
      input.addEventListener("input", function () {
        mdl.weights[k] = parseFloat(input.value);
        out.textContent = mdl.weights[k].toFixed(2);
        update();
      });
      row.appendChild(document.createTextNode(s.name));
      row.appendChild(input); row.appendChild(out);
      sliderBox.appendChild(row);
      return { input: input, out: out };
    });
  }
  function setFrame(f) {
    if (!take) return;
    f = Math.max(0, Math.min(take.n_frames - 1, f | 0));
    frame.value = f;
    frameText.textContent = "frame " + f + " / " + (take.n_frames - 1) + " (" + (f / take.fps).toFixed(2) + " s)";
    var K = take.shapes.length;
    current.weights.fill(0);
    for (var k = 0; k < K; k++) {
      var j = current.index[take.shapes[k]];
      if (j === undefined) continue;
      var w = take.offset + takeW[f * K + k] * take.scale;
      current.weights[j] = w;
      if (sliders[j]) { sliders[j].input.value = w; sliders[j].out.textContent = w.toFixed(2); }
    }
    update();
  }
  function choose(value) {
    playing = false; playBtn.textContent = "play";
    select.value = value;
    var parts = value.split(":");
    if (parts[0] === "take") {
      take = data.takes[+parts[1]];
      takeW = typed(take.weights, Int16Array);
      var mdl = model(take.model);
      show(mdl); buildSliders(mdl);
      frame.max = take.n_frames - 1; playRow.style.display = "";
      setFrame(0);
    } else {
      take = null; playRow.style.display = "none";
      var m = model(parts[1]);
      show(m); buildSliders(m);
    }
  }
  select.addEventListener("change", function () { choose(select.value); });
  frame.addEventListener("input", function () { playing = false; playBtn.textContent = "play"; setFrame(+frame.value); });
  playBtn.addEventListener("click", function () {
    playing = !playing; playBtn.textContent = playing ? "pause" : "play";
    t0 = performance.now(); f0 = +frame.value;
  });
  function tick(now) {
    if (playing && take) setFrame((f0 + Math.floor((now - t0) / 1000 * take.fps)) % take.n_frames);
    requestAnimationFrame(tick);
  }
  if (select.options.length) choose(select.options[0].value);
  requestAnimationFrame(draw);
  requestAnimationFrame(tick);

  // ---------------------------------------------------------------- #selfcheck: move a slider and a take frame
  function selfcheck() {
    var out = { webgl: !!renderer, models: Object.keys(data.models).length, takes: data.takes.length };
    choose(select.options[0].value);
    var mdl = current, best = -1, vert = -1, k = -1;
    mdl.shapes.forEach(function (s, j) {
      for (var i = 0; i < s.idx.length; i++) {
        var n = Math.hypot(s.d[3 * i], s.d[3 * i + 1], s.d[3 * i + 2]);
        if (n > best) { best = n; vert = s.idx[i]; k = j; }
      }
    });
    if (k >= 0) {
      var before = Array.from(positions.slice(3 * vert, 3 * vert + 3));
      sliders[k].input.value = "1";
      sliders[k].input.dispatchEvent(new Event("input", { bubbles: true }));
      var after = Array.from(positions.slice(3 * vert, 3 * vert + 3));
      out.slider = { shape: mdl.shapes[k].name, vertex: vert, before: before, after: after,
                     moved_mm: Math.hypot(after[0] - before[0], after[1] - before[1], after[2] - before[2]) };
    }
    if (data.takes.length) {
      choose("take:0");
      var K = take.shapes.length, fBest = 0, aBest = -1;
      for (var f = 0; f < take.n_frames; f++) {
        var a = 0;
        for (var j = 0; j < K; j++) a += Math.abs(take.offset + takeW[f * K + j] * take.scale);
        if (a > aBest) { aBest = a; fBest = f; }
      }
      frame.value = String(fBest);
      frame.dispatchEvent(new Event("input", { bubbles: true }));
      var m = current, dmax = 0;
      for (var i = 0; i < positions.length; i++) dmax = Math.max(dmax, Math.abs(positions[i] - m.neutral[i]));
      out.take = { label: take.label, frame: fBest, max_offset_mm: dmax };
      select.value = "take:" + (data.takes.length - 1);  // the menu switches take and character
      select.dispatchEvent(new Event("change", { bubbles: true }));
      out.switched = { take: take.label, model: current.label, sliders: sliders.length };
    }
    if (renderer) {
      render();
      var px = new Uint8Array(4), ctx = renderer.getContext();
      ctx.readPixels(ctx.drawingBufferWidth >> 1, ctx.drawingBufferHeight >> 1, 1, 1, ctx.RGBA, ctx.UNSIGNED_BYTE, px);
      out.centre_pixel = Array.from(px);
    }
    var table = document.querySelector("#summary table");
    out.summary_bottom_px = table ? table.getBoundingClientRect().bottom + window.scrollY : null;
    out.errors = errors.length;
    var el = document.getElementById("rb-selfcheck");
    el.textContent = JSON.stringify(out);
  }
  if (location.hash === "#selfcheck" || /[?&]selfcheck\b/.test(location.search)) {
    try { selfcheck(); } catch (e) { note("selfcheck: " + e); }
  }
})();
