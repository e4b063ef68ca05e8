// Shared by the viewer pages: test parameters from the URL and the ready/error handshake with run.mjs.
export const params = new URLSearchParams(location.search);
export const glbUrl = params.get('glb');
export const width = Number(params.get('w'));
export const height = Number(params.get('h'));
// The glTF camera node (translation, rotation x y z w) and yfov, read from the file by run.mjs.
export const camera = JSON.parse(params.get('camera'));

export function makeCanvas() {
  const canvas = document.getElementById('view');
  canvas.width = width;
  canvas.height = height;
  canvas.style.width = `${width}px`;
  canvas.style.height = `${height}px`;
  return canvas;
}

// Splat sorting is asynchronous in all three viewers: keep rendering for a while before the screenshot.
export async function settle(renderOnce, frames = 90) {
  for (let i = 0; i < frames; ++i) {
    await renderOnce();
    await new Promise((resolve) => requestAnimationFrame(resolve));
  }
}

export function ready(info) { window.__viewerInfo = info || ''; window.__ready = true; }
export function failed(error) { window.__error = String(error && error.stack || error); }
