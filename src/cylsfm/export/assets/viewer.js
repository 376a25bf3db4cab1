// cylsfm viewer: the panorama's 3D reconstruction, looked at from where the camera stood.
// Scene data (window.CYLSFM_SCENE, written by `cylsfm export viewer`): base64 little-endian arrays of the
// mesh's positions (float32, our camera axes x right, y down, z forward), texture coordinates (float32 s
// right, t down, into the panorama) and triangle indices (uint32); the panorama and the depth's colours as
// data URLs; a far textured cylinder with caps (the same arrays) shown wherever the mesh has no triangle;
// and an optional trajectory (float32 x,y,z per pose).
(function () {
  "use strict";
  var data = window.CYLSFM_SCENE;

  function decode(b64, Type) {
    var bin = atob(b64), bytes = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    return new Type(bytes.buffer);
  }

  // our axes (y down, z forward) -> three.js (y up, the camera looking along -z)
  function toThree(p) {
    for (var i = 0; i < p.length; i += 3) { p[i + 1] = -p[i + 1]; p[i + 2] = -p[i + 2]; }
    return p;
  }

  // the panorama's colours are shown as they are (sRGB values, no colour management conversion)
  THREE.ColorManagement.enabled = false;
  var renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  renderer.setSize(window.innerWidth, window.innerHeight);
  document.body.appendChild(renderer.domElement);
  var scene = new THREE.Scene();
  // a horizontal field of view of about 100 degrees, at most 75 vertically
  function verticalFov() {
    var aspect = window.innerWidth / window.innerHeight;
    var v = 2 * Math.atan(Math.tan(50 * Math.PI / 180) / aspect) * 180 / Math.PI;
    return Math.min(75, v);
  }
  var camera = new THREE.PerspectiveCamera(verticalFov(), window.innerWidth / window.innerHeight, 0.01 * data.scale, data.far);
  camera.rotation.order = "YXZ";

  function texture(url, onload) {
    var t = new THREE.TextureLoader().load(url, onload);
    t.flipY = false;  // t counts rows down from the panorama's top
    t.wrapS = THREE.RepeatWrapping;  // the seam's split column has s just above 1
    t.anisotropy = renderer.capabilities.getMaxAnisotropy();
    return t;
  }
  var pending = 2;
  function loaded() { if (--pending === 0) { update(); document.title += " (ready)"; } }
  var colourMap = texture(data.texture, loaded), depthMap = texture(data.depthTexture, loaded);

  function surface(arrays) {
    var g = new THREE.BufferGeometry();
    g.setAttribute("position", new THREE.BufferAttribute(toThree(decode(arrays.positions, Float32Array)), 3));
    g.setAttribute("uv", new THREE.BufferAttribute(decode(arrays.uv, Float32Array), 2));
    g.setIndex(new THREE.BufferAttribute(decode(arrays.indices, Uint32Array), 1));
    var m = new THREE.MeshBasicMaterial({ map: colourMap, side: THREE.DoubleSide });
    scene.add(new THREE.Mesh(g, m));
    return m;
  }
  var materials = [surface(data), surface(data.background)];

  if (data.trajectory) {
    var path = new THREE.BufferGeometry();
    path.setAttribute("position", new THREE.BufferAttribute(toThree(decode(data.trajectory, Float32Array)), 3));
    scene.add(new THREE.Line(path, new THREE.LineBasicMaterial({ color: 0xff3030 })));
    scene.add(new THREE.Points(path, new THREE.PointsMaterial({ color: 0xffff40, size: 4, sizeAttenuation: false })));
  }

  var yaw = 0, pitch = 0, forward = 0, showDepth = false;
  function update() {
    camera.rotation.set(pitch, yaw, 0);
    var dir = new THREE.Vector3(0, 0, -1).applyEuler(camera.rotation);
    camera.position.copy(dir.multiplyScalar(forward));
    renderer.render(scene, camera);
  }
  function toggle() {
    showDepth = !showDepth;
    materials.forEach(function (m) { m.map = showDepth ? depthMap : colourMap; m.needsUpdate = true; });
    document.getElementById("toggle").textContent = showDepth ? "colour" : "depth";
    update();
  }

  var dragging = null;
  var canvas = renderer.domElement;
  canvas.addEventListener("pointerdown", function (e) { dragging = { x: e.clientX, y: e.clientY }; });
  window.addEventListener("pointerup", function () { dragging = null; });
  window.addEventListener("pointermove", function (e) {
    if (!dragging) return;
    var k = camera.fov * Math.PI / 180 / window.innerHeight;
    yaw += (e.clientX - dragging.x) * k;
    pitch = Math.max(-1.5, Math.min(1.5, pitch + (e.clientY - dragging.y) * k));
    dragging = { x: e.clientX, y: e.clientY };
    update();
  });
  canvas.addEventListener("wheel", function (e) {
    e.preventDefault();
    forward -= Math.sign(e.deltaY) * 0.05 * data.scale;
    update();
  }, { passive: false });
  window.addEventListener("keydown", function (e) { if (e.key === "d" || e.key === "D") toggle(); });
  document.getElementById("toggle").addEventListener("click", toggle);
  window.addEventListener("resize", function () {
    camera.aspect = window.innerWidth / window.innerHeight;
    camera.fov = verticalFov();
    camera.updateProjectionMatrix();
    renderer.setSize(window.innerWidth, window.innerHeight);
    update();
  });
  document.getElementById("info").textContent = data.info;

  // index.html#drag=DX,DY plays a drag of DX, DY pixels through the pointer handlers above (and #depth
  // shows depth colours): what a user's drag does, for checking the page without a person
  var hash = window.location.hash.slice(1).split("&");
  update();
  hash.forEach(function (part) {
    var kv = part.split("=");
    if (kv[0] === "depth") toggle();
    if (kv[0] === "drag" && kv[1]) {
      var d = kv[1].split(",").map(Number), x0 = window.innerWidth / 2, y0 = window.innerHeight / 2;
      canvas.dispatchEvent(new PointerEvent("pointerdown", { clientX: x0, clientY: y0, bubbles: true }));
      window.dispatchEvent(new PointerEvent("pointermove", { clientX: x0 + d[0], clientY: y0 + (d[1] || 0) }));
      window.dispatchEvent(new PointerEvent("pointerup", { clientX: x0 + d[0], clientY: y0 + (d[1] || 0) }));
    }
  });
})();
