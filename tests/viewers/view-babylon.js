// Babylon.js: its glTF loader's KHR_gaussian_splatting extension and the file's own camera node.
import { Engine } from '@babylonjs/core/Engines/engine.js';
import { Scene } from '@babylonjs/core/scene.js';
import { Color4 } from '@babylonjs/core/Maths/math.color.js';
import { AppendSceneAsync } from '@babylonjs/core/Loading/sceneLoader.js';
import '@babylonjs/core/Loading/loadingScreen.js';
import '@babylonjs/loaders/glTF/2.0/index.js';
import { glbUrl, makeCanvas, settle, ready, failed } from '/common.js';

try {
  const canvas = makeCanvas();
  const engine = new Engine(canvas, false, { preserveDrawingBuffer: true, antialias: false }, false);
  engine.setHardwareScalingLevel(1);
  const scene = new Scene(engine);
  scene.clearColor = new Color4(0, 0, 0, 1);
  await AppendSceneAsync(glbUrl, scene);
  if (scene.cameras.length === 0) throw new Error('Babylon.js created no camera from the glTF camera node');
  scene.activeCamera = scene.cameras[0];
  await settle(() => scene.render());
  ready(`Babylon.js ${Engine.Version}, ${scene.meshes.length} meshes, camera '${scene.activeCamera.name}'`);
} catch (e) { failed(e); }
