// The avatar viewer page: the GLB embedded in the page as base64 (<script id="avatar">), orbit controls,
// its first animation playing in a loop; <body data-material> says what colours it shows. Bundled with
// three.js into one script by scripts/setup.sh (esbuild), so that the page opens from file:// without a
// server or the network.
import * as THREE from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";

const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.setSize(window.innerWidth, window.innerHeight);
renderer.setClearColor(0x202020);
document.body.appendChild(renderer.domElement);

const scene = new THREE.Scene();
scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 2.5));
const camera = new THREE.PerspectiveCamera(35, window.innerWidth / window.innerHeight, 0.05, 50);
camera.position.set(0, 0.2, 4.0);
const controls = new OrbitControls(camera, renderer.domElement);
controls.target.set(0, 0, 0);
controls.update();

const b64 = document.getElementById("avatar").textContent.trim();
const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
const clock = new THREE.Clock();
let mixer = null;
window.viewerFrames = 0;
new GLTFLoader().parse(bytes.buffer, "", (gltf) => {
  scene.add(gltf.scene);
  // Unlit, like the volume render: the baked texture when the GLB has one, else the vertex colours.
  const shown = [];
  gltf.scene.traverse((o) => {
    if (o.isMesh) {
      const map = o.material.map || null;
      o.material = map
        ? new THREE.MeshBasicMaterial({ map, side: THREE.DoubleSide })
        : new THREE.MeshBasicMaterial({ vertexColors: true, side: THREE.DoubleSide });
      shown.push(map ? `texture ${map.image.width}x${map.image.height}` : "vertex colours");
      o.frustumCulled = false;
    }
  });
  document.body.dataset.material = shown.join(", ");
  const box = new THREE.Box3().setFromObject(gltf.scene);
  const centre = box.getCenter(new THREE.Vector3());
  controls.target.copy(centre);
  camera.position.set(centre.x, centre.y + 0.1, centre.z + 2.2 * Math.max(1.0, box.getSize(new THREE.Vector3()).y));
  controls.update();
  if (gltf.animations.length) {
    mixer = new THREE.AnimationMixer(gltf.scene);
    mixer.clipAction(gltf.animations[0]).play();
  }
  document.title = "avatar: loaded";
}, (err) => { document.title = "avatar: error " + err; });

window.addEventListener("resize", () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
});
renderer.setAnimationLoop(() => {
  if (mixer) mixer.update(clock.getDelta());
  renderer.render(scene, camera);
  window.viewerFrames += 1;
  window.viewerTime = mixer ? mixer.time : 0; // seconds of animation played, for the page's tests
});
