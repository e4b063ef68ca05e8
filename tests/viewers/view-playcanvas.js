// PlayCanvas: container asset (KHR_gaussian_splatting -> gsplat component); camera placed from the glTF camera node.
import * as pc from 'playcanvas';
import { glbUrl, width, height, camera, makeCanvas, settle, ready, failed } from '/common.js';

try {
  const canvas = makeCanvas();
  const device = await pc.createGraphicsDevice(canvas, { deviceTypes: ['webgl2'], antialias: false, preserveDrawingBuffer: true });
  device.maxPixelRatio = 1;
  const options = new pc.AppOptions();
  options.graphicsDevice = device;
  options.componentSystems = [pc.RenderComponentSystem, pc.CameraComponentSystem, pc.GSplatComponentSystem];
  options.resourceHandlers = [pc.ContainerHandler, pc.TextureHandler, pc.GSplatHandler];
  const app = new pc.AppBase(canvas);
  app.init(options);
  app.setCanvasFillMode(pc.FILLMODE_NONE, width, height);
  app.setCanvasResolution(pc.RESOLUTION_FIXED, width, height);
  app.start();
  const asset = await new Promise((resolve, reject) => {
    app.assets.loadFromUrl(glbUrl, 'container', (err, a) => (err ? reject(new Error(err)) : resolve(a)));
  });
  const entity = asset.resource.instantiateRenderEntity();
  app.root.addChild(entity);
  const cam = new pc.Entity('camera');
  cam.addComponent('camera', {
    clearColor: new pc.Color(0, 0, 0, 1), fov: camera.yfov * 180 / Math.PI, horizontalFov: false,
    nearClip: 0.01, farClip: 1000,
  });
  cam.setPosition(...camera.translation);
  cam.setRotation(new pc.Quat(...camera.rotation));
  app.root.addChild(cam);
  await settle(async () => app.render());
  ready(`PlayCanvas ${pc.version}`);
} catch (e) { failed(e); }
