// three.js: GLTFLoader with GLTFGaussianSplatLoaderExtension, WebGPURenderer on its WebGL 2 backend, file camera.
import * as THREE from 'three/webgpu';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { GLTFGaussianSplatLoaderExtension } from 'three/addons/loaders/GLTFGaussianSplatLoaderExtension.js';
import { glbUrl, width, height, makeCanvas, settle, ready, failed } from '/common.js';

try {
  const canvas = makeCanvas();
  const renderer = new THREE.WebGPURenderer({ canvas, antialias: false, forceWebGL: true });
  renderer.setPixelRatio(1);
  renderer.setSize(width, height, false);
  renderer.setClearColor(0x000000, 1);
  // The splats' colours are display-referred sRGB already (colorSpace srgb_rec709_display): blend and show them as
  // they are. three.js's default sRGB output transform would encode them a second time (19.9 dB instead).
  renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
  await renderer.init();
  const loader = new GLTFLoader();
  loader.register((parser) => new GLTFGaussianSplatLoaderExtension(parser));
  const gltf = await loader.loadAsync(glbUrl);
  if (gltf.cameras.length === 0) throw new Error('three.js created no camera from the glTF camera node');
  const camera = gltf.cameras[0];
  camera.aspect = width / height;
  camera.updateProjectionMatrix();
  const scene = gltf.scene;
  scene.updateMatrixWorld(true);
  await settle(async () => renderer.render(scene, camera));
  ready(`three.js r${THREE.REVISION}, backend ${renderer.backend.constructor.name}`);
} catch (e) { failed(e); }
