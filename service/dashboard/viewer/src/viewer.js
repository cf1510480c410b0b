// The job page's 3D view: Gaussian splat scenes on the PlayCanvas engine (WebGL 2), orbited with the pointer or
// the arrow keys, with the job's mirror planes drawn in. Bundled by ../build.mjs into ../../static/viewer.js.
//
// Scenes come in as bytes the page fetched with its API key (a `.sog` bundle or a `.ply`), never as addresses the
// engine would fetch itself. Their data are in the PLY's axes (y down); a root entity turned 180 degrees about z
// shows them y-up, and the mirror planes, given in the same data axes, hang under that root too.

import {
  AppBase,
  AppOptions,
  Asset,
  CameraComponentSystem,
  Color,
  Entity,
  FILLMODE_NONE,
  GSplatComponentSystem,
  GSplatHandler,
  RESOLUTION_AUTO,
  TextureHandler,
  Vec3,
  WebglGraphicsDevice,
} from "playcanvas";

const AWAKE_MS = 1500; // frames keep coming this long after a change (the depth sort lands a few frames later)
const FRAMING_SAMPLE = 20000; // centres sampled to frame the scene
const PITCH_LIMIT = 89;

function sampleCentres(centres) {
  const count = centres.length / 3;
  const step = Math.max(1, Math.floor(count / FRAMING_SAMPLE));
  const points = [];
  for (let i = 0; i < count; i += step) points.push([centres[3 * i], centres[3 * i + 1], centres[3 * i + 2]]);
  return points;
}

function quantile(values, q) {
  const sorted = Float64Array.from(values).sort();
  return sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
}

// The median point and the distance that holds 90% of the centres: stray Gaussians far out do not shrink the view.
function framing(resource) {
  const points = resource.centers ? sampleCentres(resource.centers) : [];
  if (!points.length) {
    const box = resource.aabb;
    return { centre: [box.center.x, box.center.y, box.center.z], radius: Math.max(box.halfExtents.length(), 1e-3) };
  }
  const centre = [0, 1, 2].map((axis) => quantile(points.map((p) => p[axis]), 0.5));
  const radius = quantile(points.map((p) => Math.hypot(p[0] - centre[0], p[1] - centre[1], p[2] - centre[2])), 0.9);
  return { centre, radius: Math.max(radius, 1e-3) };
}

function planeBasis(normal) {
  const n = new Vec3(...normal).normalize();
  const helper = Math.abs(n.x) < 0.9 ? new Vec3(1, 0, 0) : new Vec3(0, 1, 0);
  const u = new Vec3().cross(n, helper).normalize();
  const v = new Vec3().cross(n, u).normalize();
  return { n, u, v };
}

export class SplatViewer {
  // A viewer drawing in `canvas`; throws when the browser offers no WebGL 2.
  static create(canvas) {
    return new SplatViewer(canvas, new WebglGraphicsDevice(canvas, { antialias: false }));
  }

  constructor(canvas, device) {
    const options = new AppOptions();
    options.graphicsDevice = device;
    options.componentSystems = [CameraComponentSystem, GSplatComponentSystem];
    options.resourceHandlers = [TextureHandler, GSplatHandler];
    this.app = new AppBase(canvas);
    this.app.init(options);
    this.app.setCanvasFillMode(FILLMODE_NONE);
    this.app.setCanvasResolution(RESOLUTION_AUTO);
    this.app.autoRender = false;
    this.canvas = canvas;
    this.scenes = new Map(); // name -> {entity, framing}
    this.planes = []; // {points: [Vec3 x 4], colour}
    this.showPlanes = true;
    // Start on the data's -z side looking along +z, as capture cameras in OpenCV axes look, turned a little.
    this.yaw = 200;
    this.pitch = 15;
    this.distance = 3;
    this.target = new Vec3();
    this.awakeUntil = 0;

    this.root = new Entity("data axes");
    this.root.setLocalEulerAngles(0, 0, 180);
    this.app.root.addChild(this.root);
    this.camera = new Entity("camera");
    this.camera.addComponent("camera", { clearColor: new Color(0.07, 0.08, 0.1) });
    this.app.root.addChild(this.camera);

    this.app.on("update", () => this.frame());
    new ResizeObserver(() => this.resize()).observe(canvas);
    this.bindInput();
    this.resize();
    this.app.start();
  }

  resize() {
    const { clientWidth, clientHeight } = this.canvas;
    if (clientWidth && clientHeight) this.app.resizeCanvas(clientWidth, clientHeight);
    this.wake();
  }

  wake() {
    this.awakeUntil = performance.now() + AWAKE_MS;
  }

  frame() {
    const t = this.target;
    const yaw = (this.yaw * Math.PI) / 180;
    const pitch = (this.pitch * Math.PI) / 180;
    const d = this.distance;
    this.camera.setPosition(t.x + d * Math.sin(yaw) * Math.cos(pitch), t.y + d * Math.sin(pitch),
      t.z + d * Math.cos(yaw) * Math.cos(pitch));
    this.camera.lookAt(t);
    if (this.showPlanes) this.drawPlanes();
    this.app.renderNextFrame = performance.now() < this.awakeUntil;
  }

  drawPlanes() {
    const toWorld = this.root.getWorldTransform();
    for (const { points, colour } of this.planes) {
      const corners = points.map((p) => toWorld.transformPoint(p, new Vec3()));
      const lines = [];
      for (let i = 0; i < corners.length; i += 1) lines.push(corners[i], corners[(i + 1) % corners.length]);
      // The two centre lines mark where the plane crosses the scene's middle.
      const mid = (a, b) => new Vec3().lerp(a, b, 0.5);
      lines.push(mid(corners[0], corners[1]), mid(corners[2], corners[3]));
      lines.push(mid(corners[1], corners[2]), mid(corners[3], corners[0]));
      this.app.drawLines(lines, colour, false);
    }
  }

  bindInput() {
    const canvas = this.canvas;
    let last = null;
    canvas.addEventListener("pointerdown", (event) => {
      last = [event.clientX, event.clientY];
      canvas.setPointerCapture(event.pointerId);
    });
    canvas.addEventListener("pointermove", (event) => {
      if (!last) return;
      this.orbit(-(event.clientX - last[0]) * 0.3, (event.clientY - last[1]) * 0.3);
      last = [event.clientX, event.clientY];
    });
    const release = () => {
      last = null;
    };
    canvas.addEventListener("pointerup", release);
    canvas.addEventListener("pointercancel", release);
    canvas.addEventListener(
      "wheel",
      (event) => {
        event.preventDefault();
        this.zoom(Math.exp(event.deltaY * 0.001));
      },
      { passive: false },
    );
    canvas.addEventListener("keydown", (event) => {
      const moves = { ArrowLeft: [5, 0], ArrowRight: [-5, 0], ArrowUp: [0, 5], ArrowDown: [0, -5] };
      if (moves[event.key]) this.orbit(...moves[event.key]);
      else if (event.key === "+" || event.key === "=") this.zoom(0.9);
      else if (event.key === "-") this.zoom(1.1);
      else return;
      event.preventDefault();
    });
  }

  orbit(yaw, pitch) {
    this.yaw = (this.yaw + yaw) % 360;
    this.pitch = Math.max(-PITCH_LIMIT, Math.min(PITCH_LIMIT, this.pitch + pitch));
    this.wake();
  }

  zoom(factor) {
    const radius = this.radius ?? 1;
    this.distance = Math.max(radius * 0.05, Math.min(radius * 50, this.distance * factor));
    this.wake();
  }

  // Adds scene `name` from `bytes` (ArrayBuffer) whose format `filename` names (.sog, .ply, .compressed.ply).
  load(name, bytes, filename) {
    return new Promise((resolve, reject) => {
      // The engine's parsers read `contents` as a fetch Response (the PLY parser streams its body).
      const contents = new Response(bytes);
      const asset = new Asset(name, "gsplat", { url: `${name}/${filename}`, filename, contents });
      asset.once("load", () => {
        const entity = new Entity(name);
        entity.addComponent("gsplat", { asset });
        entity.enabled = false;
        this.root.addChild(entity);
        this.scenes.set(name, { entity, framing: framing(asset.resource) });
        resolve();
      });
      asset.once("error", (err) => reject(new Error(String(err))));
      this.app.assets.add(asset);
      this.app.assets.load(asset);
    });
  }

  // Shows scene `name` alone; the first scene shown frames the view, later ones keep it for comparison.
  show(name) {
    const scene = this.scenes.get(name);
    if (!scene) throw new Error(`no scene ${name}`);
    for (const [other, { entity }] of this.scenes) entity.enabled = other === name;
    if (this.radius === undefined) this.frameOn(scene.framing);
    this.wake();
  }

  frameOn({ centre, radius }) {
    this.radius = radius;
    this.centre = centre;
    this.root.getWorldTransform().transformPoint(new Vec3(...centre), this.target);
    this.distance = radius * 2.5;
    this.camera.camera.nearClip = radius * 1e-3;
    this.camera.camera.farClip = radius * 200;
    this.setMirrors(this.mirrors ?? []);
  }

  // mirrors: [{normal: [x, y, z], offset, colour: "#rrggbb"}] in the data axes; squares around the scene centre.
  setMirrors(mirrors) {
    this.mirrors = mirrors;
    const centre = new Vec3(...(this.centre ?? [0, 0, 0]));
    const half = 1.2 * (this.radius ?? 1);
    this.planes = mirrors.map(({ normal, offset, colour }) => {
      const { n, u, v } = planeBasis(normal);
      const foot = centre.clone().sub(n.clone().mulScalar(centre.dot(n) - offset));
      const corner = (a, b) => foot.clone().add(u.clone().mulScalar(a * half)).add(v.clone().mulScalar(b * half));
      return { points: [corner(-1, -1), corner(1, -1), corner(1, 1), corner(-1, 1)], colour: new Color().fromString(colour) };
    });
    this.wake();
  }

  setPlanesVisible(visible) {
    this.showPlanes = visible;
    this.wake();
  }
}
