// cylsfm viewer: the panorama's 3D reconstruction, looked at from where the camera stood.
// Scene data (window.CYLSFM_SCENE, written by `cylsfm export viewer`): base64 little-endian arrays of
// positions (float32, our camera axes x right, y down, z forward), colours and depth colours (uint8 RGB),
// triangle indices (uint32), and an optional trajectory (float32 x,y,z per pose).
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
  var camera = new THREE.PerspectiveCamera(75, window.innerWidth / window.innerHeight, 0.01 * data.scale, 1000 * data.scale);
  camera.rotation.order = "YXZ";

  var geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(toThree(decode(data.positions, Float32Array)), 3));
  var colours = new THREE.BufferAttribute(decode(data.colours, Uint8Array), 3, true);
  var depthColours = new THREE.BufferAttribute(decode(data.depthColours, Uint8Array), 3, true);
  geometry.setAttribute("color", colours);
  var indices = decode(data.indices, Uint32Array);
  var material, object;
  if (indices.length) {
    geometry.setIndex(new THREE.BufferAttribute(indices, 1));
    material = new THREE.MeshBasicMaterial({ vertexColors: true, side: THREE.DoubleSide });
    object = new THREE.Mesh(geometry, material);
  } else {
    material = new THREE.PointsMaterial({ vertexColors: true, size: 2, sizeAttenuation: false });
    object = new THREE.Points(geometry, material);
  }
  scene.add(object);

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
    geometry.setAttribute("color", showDepth ? depthColours : colours);
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
  document.title += " (ready)";
})();
