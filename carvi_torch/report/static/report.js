/* carvi_torch report: pages of object cards, a class filter, lazy 3D viewers.
 *
 * Works from disk (file://): every data file is a classic script that registers itself
 * (carviReport.index, carviReport.mesh), never fetch()/XHR. All viewers share one WebGL
 * renderer and copy its picture into their own 2D canvas, so a page of many cards needs one
 * WebGL context. <body data-ready="1"> once every card of the current page has its viewer drawn
 * or its failure shown; each card says which in data-viewer ("ok", "failed", "none").
 */
(function () {
  'use strict';
  var R = window.carviReport = {};
  var S = {meta: {}, cards: [], byClass: {}, pending: {}, token: 0};
  var W = 208, H = 208;
  var gl = null;  // the shared renderer; false: WebGL unavailable (gl_reason says why)
  var glReason = '';

  R.index = function (meta, cards) { S.meta = meta; S.cards = cards; };

  R.mesh = function (key, data) {
    var cb = S.pending[key];
    if (cb) { delete S.pending[key]; cb(null, data); }
  };

  function el(tag, attrs, text) {
    var e = document.createElement(tag);
    for (var k in (attrs || {})) { e.setAttribute(k, attrs[k]); }
    if (text !== undefined && text !== null) { e.textContent = String(text); }
    return e;
  }

  function fmt(v, digits) { return (v === undefined || v === null) ? '-' : Number(v).toFixed(digits); }

  function renderer() {
    if (gl !== null) { return gl; }
    try {
      if (typeof THREE === 'undefined' || typeof THREE.OrbitControls === 'undefined') {
        throw new Error('the three.js scripts did not load');
      }
      gl = new THREE.WebGLRenderer({antialias: true, preserveDrawingBuffer: true});
      gl.setSize(W, H);
      gl.setClearColor(0xf4f4f4, 1);
    } catch (e) {
      gl = false;
      glReason = 'WebGL unavailable: ' + (e && e.message ? e.message : e);
    }
    return gl;
  }

  function decode(b64, Type) {
    var s = atob(b64), n = s.length, u = new Uint8Array(n);
    for (var i = 0; i < n; i++) { u[i] = s.charCodeAt(i); }
    return new Type(u.buffer);
  }

  function geometry(d) {
    var q = decode(d.positions, Int16Array), p = new Float32Array(q.length), h = d.half / 32767;
    for (var i = 0; i < q.length; i += 3) {
      // reference camera frame (x right, y down, z away) -> three.js (y up, z towards the viewer)
      p[i] = q[i] * h; p[i + 1] = -q[i + 1] * h; p[i + 2] = -q[i + 2] * h;
    }
    var g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.BufferAttribute(p, 3));
    g.setIndex(new THREE.BufferAttribute(decode(d.index, d.index_bits === 16 ? Uint16Array : Uint32Array), 1));
    g.computeVertexNormals();
    return g;
  }

  function viewer(box, d) {
    var r = renderer();
    if (!r) { throw new Error(glReason); }
    var scene = new THREE.Scene();
    scene.add(new THREE.HemisphereLight(0xffffff, 0x667788, 0.9));
    var cam = new THREE.PerspectiveCamera(30, W / H, d.half * 0.05, d.half * 20);
    cam.position.set(0, 0, d.half * 4.2);
    var sun = new THREE.DirectionalLight(0xffffff, 0.6);
    sun.position.set(1, 1, 2);
    cam.add(sun);
    scene.add(cam);
    scene.add(new THREE.Mesh(geometry(d), new THREE.MeshLambertMaterial({color: 0x8fb0d8, side: THREE.DoubleSide})));
    var canvas = el('canvas', {width: W, height: H, 'class': 'view3d', title: 'drag: rotate, wheel: zoom'});
    var ctx = canvas.getContext('2d');
    var controls = new THREE.OrbitControls(cam, canvas);
    function draw() {
      r.render(scene, cam);
      ctx.clearRect(0, 0, W, H);
      ctx.drawImage(r.domElement, 0, 0, W, H);
    }
    controls.addEventListener('change', draw);
    box.textContent = '';
    box.appendChild(canvas);
    draw();
    // test hook: the share of the view the shape covers (pixels unlike the background)
    var px = ctx.getImageData(0, 0, W, H).data, hit = 0;
    for (var i = 0; i < px.length; i += 4) {
      if (Math.abs(px[i] - 0xf4) + Math.abs(px[i + 1] - 0xf4) + Math.abs(px[i + 2] - 0xf4) > 24) { hit++; }
    }
    box.setAttribute('data-drawn', (hit / (W * H)).toFixed(3));
  }

  function loadMesh(c, done) {
    var called = false;
    function once(err, d) { if (!called) { called = true; done(err, d); } }
    S.pending[c.key] = once;
    var s = el('script', {src: c.mesh});
    s.onerror = function () { delete S.pending[c.key]; once('mesh data missing (' + c.mesh + ')'); };
    s.onload = function () {
      if (S.pending[c.key]) { delete S.pending[c.key]; once('mesh data damaged (' + c.mesh + ')'); }
    };
    document.head.appendChild(s);
  }

  function stats(c) {
    var rows = [['quality', fmt(c.quality, 3)], ['proposal score', fmt(c.score, 4)],
      ['silhouette IoU', fmt(c.iou, 3)], ['kp residual SfM / refined', fmt(c.residual_sfm, 1) + ' / ' + fmt(c.residual, 1) + ' px'],
      ['azimuth / elevation', fmt(c.az, 1) + ' / ' + fmt(c.el, 1) + ' deg'],
      ['camera / surrogates', (c.camera_from || '-') + ' / ' + (c.surrogates_from || '-')]];
    var dl = el('dl', {'class': 'stats'});
    rows.forEach(function (r) { dl.appendChild(el('dt', null, r[0])); dl.appendChild(el('dd', null, r[1])); });
    return dl;
  }

  function card(c) {
    var d = el('div', {'class': 'card' + (c.skipped || c.problems ? ' bad' : ''), 'data-annotation-id': c.id,
      'data-class': c.cls, 'data-viewer': 'pending'});
    d.appendChild(el('h3', null, (S.meta.names[c.cls] || c.cls) + ' #' + c.id));
    if (c.source) { d.appendChild(el('div', {'class': 'source'}, c.source)); }
    if (c.skipped) { d.appendChild(el('div', {'class': 'reason'}, 'skipped: ' + c.skipped)); }
    (c.problems || []).forEach(function (p) { d.appendChild(el('div', {'class': 'reason'}, p)); });
    var pics = el('div', {'class': 'pics'});
    if (c.img) {
      pics.appendChild(el('img', {src: c.img, alt: 'overlay of ' + c.id, width: W, height: H, 'class': 'overlay'}));
    }
    var box = el('div', {'class': 'view3d-box'}, c.mesh ? 'loading 3D view...' : 'no 3D view');
    pics.appendChild(box);
    d.appendChild(pics);
    var legend = document.getElementById('legend-template');
    if (legend) { var l = legend.cloneNode(true); l.removeAttribute('id'); d.appendChild(l); }
    d.appendChild(stats(c));
    var links = el('div', {'class': 'links'});
    ['mesh', 'voxels', 'cameras'].forEach(function (k) {
      if (c.files && c.files[k]) { links.appendChild(el('a', {href: c.files[k]}, k)); }
    });
    d.appendChild(links);
    return {node: d, box: box};
  }

  function parseHash() {
    var h = {};
    location.hash.replace(/^#/, '').split('&').forEach(function (kv) {
      var i = kv.indexOf('=');
      if (i > 0) {
        // a malformed escape (a hand-typed '%') drops that key: no class named means all classes
        try { h[decodeURIComponent(kv.slice(0, i))] = decodeURIComponent(kv.slice(i + 1)); } catch (e) { }
      }
    });
    return h;
  }

  function show() {
    var h = parseHash(), cls = h['class'] || 'all', per = S.meta.per_page;
    var list = cls === 'all' ? S.cards : S.cards.filter(function (c) { return c.cls === cls; });
    var pages = Math.max(1, Math.ceil(list.length / per));
    var page = Math.min(Math.max(1, parseInt(h.page || '1', 10) || 1), pages);
    var token = ++S.token;
    document.body.setAttribute('data-ready', '0');
    document.getElementById('class-filter').value = cls;
    document.getElementById('page-info').textContent = 'page ' + page + ' of ' + pages + ' (' + list.length +
      ' objects, worst first by ' + S.meta.sort_by + ')';
    document.getElementById('prev').disabled = page <= 1;
    document.getElementById('next').disabled = page >= pages;
    var grid = document.getElementById('cards');
    grid.textContent = '';
    var shown = list.slice((page - 1) * per, page * per), left = shown.length;
    function finished(node, state, text, box) {
      if (token !== S.token) { return; }
      node.setAttribute('data-viewer', state);
      if (text) { box.textContent = text; }
      if (--left === 0) { document.body.setAttribute('data-ready', '1'); }
    }
    shown.forEach(function (c) {
      var made = card(c);
      grid.appendChild(made.node);
      if (!c.mesh) { finished(made.node, 'none', null, made.box); return; }
      loadMesh(c, function (err, d) {
        if (err) { finished(made.node, 'failed', err, made.box); return; }
        try { viewer(made.box, d); finished(made.node, 'ok', null, made.box); } catch (e) {
          finished(made.node, 'failed', 'no 3D view: ' + (e && e.message ? e.message : e), made.box);
        }
      });
    });
    if (shown.length === 0) { document.body.setAttribute('data-ready', '1'); }
    R.state = {cls: cls, page: page, pages: pages, shown: shown.length, webgl: gl === null ? null : !!gl};
  }

  function go(cls, page) { location.hash = 'class=' + encodeURIComponent(cls) + '&page=' + page; }

  R.start = function () {
    if (!S.meta.per_page) {
      document.getElementById('cards').textContent = 'cards.js did not load: no object cards to show';
      document.body.setAttribute('data-ready', '1');
      return;
    }
    var sel = document.getElementById('class-filter');
    sel.addEventListener('change', function () { go(sel.value, 1); });
    document.getElementById('prev').addEventListener('click', function () {
      go(sel.value, (R.state ? R.state.page : 1) - 1);
    });
    document.getElementById('next').addEventListener('click', function () {
      go(sel.value, (R.state ? R.state.page : 1) + 1);
    });
    window.addEventListener('hashchange', show);
    show();
  };
})();
