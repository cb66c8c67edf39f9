// The bone in 3D: the carved surface from mesh chunks, the burr and its shaft at the latest
// pose, the force arrow, a section plane. Everything is in the server frame, mm (the mesh is
// asked for with frame=server, and telemetry's pose is in that frame).
import * as THREE from "three";
import { OrbitControls } from "three/addons/OrbitControls.js";

const PALETTE = [0xe8dcc0, 0xc9a36b, 0x9fb8d9, 0xb7d39a, 0xd7a3c9, 0xa3d7d0, 0xd9c36b];
const FORBIDDEN = 0xff2a55;
/** The force arrow's length per newton, mm (a 1.8 N cut draws 7 mm). */
const ARROW_MM_PER_N = 4;
/** Redraws at most this often while something moves, Hz. */
const MAX_FPS = 30;
/** Without a GPU (a software rasterizer) a frame costs a core's milliseconds, which the hot
 * loop on the same machine should keep: fewer frames, a quarter of the pixels, no
 * multisampling. */
const SOFTWARE = { maxFps: 2, pixelRatio: 0.5 };

/** The WebGL implementation's name, from a throwaway context (before the renderer, whose
 * antialiasing is fixed when its context is made). */
function glRendererName() {
  const gl = document.createElement("canvas").getContext("webgl2");
  if (!gl) return "";
  const debug = gl.getExtension("WEBGL_debug_renderer_info");
  const name = debug ? String(gl.getParameter(debug.UNMASKED_RENDERER_WEBGL)) : "";
  const lose = gl.getExtension("WEBGL_lose_context");
  if (lose) lose.loseContext();
  return name;
}

export class BoneScene {
  /** @param {HTMLElement} container */
  constructor(container) {
    this.container = container;
    this.glRenderer = glRendererName();
    // #render=full in the link keeps the full rate and resolution on a software renderer.
    const full = new URLSearchParams(window.location.hash.slice(1)).get("render") === "full";
    this.software = !full && /swiftshader|llvmpipe|softpipe|software/i.test(this.glRenderer);
    this.maxFps = this.software ? SOFTWARE.maxFps : MAX_FPS;
    this.renderer = new THREE.WebGLRenderer({ antialias: !this.software });
    this.renderer.setPixelRatio(this.software ? SOFTWARE.pixelRatio : Math.min(window.devicePixelRatio, 2));
    this.renderer.localClippingEnabled = true;
    this.renderer.setClearColor(0x151922);
    container.appendChild(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.1, 5000);
    this.camera.up.set(0, 0, 1);
    this.camera.position.set(60, -80, 60);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => this.invalidate());
    // A soft fill, and a key light from the camera's upper left at a grazing angle: a groove
    // seen from straight above shows in its walls' shading.
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x404050, 0.9));
    this.light = new THREE.DirectionalLight(0xffffff, 2.4);
    this.light.position.set(-0.7, 0.7, 0.45);
    this.camera.add(this.light);
    this.camera.add(this.light.target);
    this.light.target.position.set(0, 0, -1);
    this.scene.add(this.camera);

    this.section = new THREE.Plane(new THREE.Vector3(1, 0, 0), 1e9);
    // Lambert: diffuse light is all bone needs, at a fraction of a physical material's cost.
    this.boneMaterial = new THREE.MeshLambertMaterial({
      vertexColors: true, side: THREE.DoubleSide, clippingPlanes: [this.section],
    });
    this.bone = new THREE.Group();
    this.scene.add(this.bone);
    this.meshes = new Map();
    this.labelColors = new Map();
    this.box = null;

    // Forbidden structures, seen through the bone (they are inside it until exposed).
    this.forbidden = new THREE.Mesh(new THREE.BufferGeometry(), new THREE.MeshBasicMaterial({
      color: FORBIDDEN, transparent: true, opacity: 0.45, depthTest: false, depthWrite: false,
      side: THREE.DoubleSide,
    }));
    this.forbidden.renderOrder = 5;
    this.forbidden.visible = false;
    this.showForbidden = true;
    this.scene.add(this.forbidden);

    this.tool = new THREE.Group();
    this.tool.visible = false;
    this.scene.add(this.tool);
    this.burrMaterial = new THREE.MeshStandardMaterial({ color: 0xb0b8c8, metalness: 0.6, roughness: 0.35 });
    this.shaftMaterial = new THREE.MeshStandardMaterial({ color: 0x8890a0, metalness: 0.5, roughness: 0.4 });
    this.burr = new THREE.Mesh(new THREE.SphereGeometry(1, 32, 16), this.burrMaterial);
    this.shaft = new THREE.Mesh(new THREE.CylinderGeometry(1, 1, 1, 24), this.shaftMaterial);
    this.tool.add(this.burr, this.shaft);
    this.arrow = new THREE.ArrowHelper(new THREE.Vector3(0, 0, 1), new THREE.Vector3(), 1, 0xffe14f);
    this.arrow.visible = false;
    // Drawn over everything: it starts inside the burr, and the shaft often hides it.
    for (const part of [this.arrow.line, this.arrow.cone]) {
      part.material.depthTest = false;
      part.renderOrder = 10;
    }
    this.scene.add(this.arrow);

    this.showTool = true;
    this.scheduled = false;
    this.lastDraw = -Infinity;
    this.frames = 0;
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
  }

  /** Asks for a frame: drawn at the next animation frame allowed by the frame cap. Nothing
   * runs while nothing changes (no animation loop: an idle page costs nothing). */
  invalidate() {
    if (this.scheduled) return;
    this.scheduled = true;
    const wait = Math.max(0, this.lastDraw + 1000 / this.maxFps - performance.now());
    setTimeout(() => requestAnimationFrame((now) => {
      this.scheduled = false;
      this.lastDraw = now;
      this.renderer.render(this.scene, this.camera);
      this.frames += 1;
    }), wait);
  }

  resize() {
    const w = Math.max(100, this.container.clientWidth);
    const h = Math.max(100, this.container.clientHeight);
    this.renderer.setSize(w, h);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.invalidate();
  }

  /** Colours per material label; forbidden ones stand out. @param {Array} materials GET …/materials */
  setMaterials(materials) {
    this.labelColors.clear();
    materials.forEach((m, i) => {
      this.labelColors.set(m.label, new THREE.Color(m.forbidden ? FORBIDDEN : PALETTE[i % PALETTE.length]));
    });
    for (const [key, mesh] of this.meshes) this.colour(mesh.geometry, mesh.userData.labels, key);
    this.invalidate();
  }

  colour(geometry, labels) {
    const colours = new Float32Array(labels.length * 3);
    const fallback = new THREE.Color(PALETTE[0]);
    for (let i = 0; i < labels.length; i += 1) {
      const c = this.labelColors.get(labels[i]) || fallback;
      colours[3 * i] = c.r; colours[3 * i + 1] = c.g; colours[3 * i + 2] = c.b;
    }
    geometry.setAttribute("color", new THREE.BufferAttribute(colours, 3));
  }

  clearBone() {
    for (const mesh of this.meshes.values()) {
      this.bone.remove(mesh);
      mesh.geometry.dispose();
    }
    this.meshes.clear();
    this.invalidate();
  }

  /** Adds, replaces (chunk) or removes (null) one mesh chunk (mesh.js's ChunkCopy callback). */
  setChunk(key, chunk) {
    const old = this.meshes.get(key);
    if (old) {
      this.bone.remove(old);
      old.geometry.dispose();
      this.meshes.delete(key);
    }
    if (chunk) {
      const g = new THREE.BufferGeometry();
      g.setAttribute("position", new THREE.BufferAttribute(chunk.positions, 3));
      g.setAttribute("normal", new THREE.BufferAttribute(chunk.normals, 3));
      g.setIndex(new THREE.BufferAttribute(chunk.triangles, 1));
      this.colour(g, chunk.labels);
      const mesh = new THREE.Mesh(g, this.boneMaterial);
      mesh.userData.labels = chunk.labels;
      this.bone.add(mesh);
      this.meshes.set(key, mesh);
    }
    this.invalidate();
  }

  /** The forbidden structures' surface (triangle soup, mm), or null: none. */
  setForbidden(triangles) {
    this.forbidden.geometry.dispose();
    this.forbidden.geometry = new THREE.BufferGeometry();
    if (triangles && triangles.positions.length) {
      this.forbidden.geometry.setAttribute("position", new THREE.BufferAttribute(triangles.positions, 3));
      this.forbidden.geometry.setAttribute("normal", new THREE.BufferAttribute(triangles.normals, 3));
    }
    this.forbidden.visible = this.showForbidden && Boolean(triangles && triangles.positions.length);
    this.invalidate();
  }

  setForbiddenShown(shown) {
    this.showForbidden = shown;
    this.forbidden.visible = shown && this.forbidden.geometry.getAttribute("position") !== undefined;
    this.invalidate();
  }

  /** The bone's box from its REST info (server frame, mm); frames the camera on the first. */
  setBoneBox(info, reframe = false) {
    const box = new THREE.Box3();
    const [ni, nj, nk] = info.shape;
    const d = info.direction;
    for (const ci of [0, ni - 1]) for (const cj of [0, nj - 1]) for (const ck of [0, nk - 1]) {
      const g = [ci * info.spacing_mm[0], cj * info.spacing_mm[1], ck * info.spacing_mm[2]];
      box.expandByPoint(new THREE.Vector3(
        info.origin_mm[0] + d[0][0] * g[0] + d[0][1] * g[1] + d[0][2] * g[2],
        info.origin_mm[1] + d[1][0] * g[0] + d[1][1] * g[1] + d[1][2] * g[2],
        info.origin_mm[2] + d[2][0] * g[0] + d[2][1] * g[1] + d[2][2] * g[2]));
    }
    const first = this.box === null;
    this.box = box;
    if (first || reframe) this.view("iso");
    return box;
  }

  /** Looks at the bone from a named side: iso, top, front, side. */
  view(name) {
    if (!this.box) return;
    const centre = this.box.getCenter(new THREE.Vector3());
    const size = this.box.getSize(new THREE.Vector3()).length();
    const dirs = {
      iso: [0.55, -0.75, 0.6], top: [0, -0.0001, 1], front: [0, -1, 0.0001], side: [1, 0, 0.0001],
    };
    const dir = new THREE.Vector3(...(dirs[name] || dirs.iso)).normalize();
    this.camera.position.copy(centre).addScaledVector(dir, size * 1.25);
    this.camera.near = size / 100;
    this.camera.far = size * 20;
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(centre);
    this.controls.update();
    this.invalidate();
  }

  /** Points the camera at a point (mm) from a given distance, looking down. */
  lookDownAt(point, distanceMm) {
    this.controls.target.set(...point);
    this.camera.position.set(point[0], point[1] - 0.0001, point[2] + distanceMm);
    this.controls.update();
    this.invalidate();
  }

  /** The section plane: axis 'x' | 'y' | 'z' | '' (off), at a share 0..1 of the bone's box.
   * The half kept is the one away from the camera, so the cut faces it; flip keeps the other. */
  setSection(axis, share, flip) {
    if (!axis || !this.box) {
      this.section.set(new THREE.Vector3(1, 0, 0), 1e9);
    } else {
      const i = { x: 0, y: 1, z: 2 }[axis];
      const lo = this.box.min.getComponent(i);
      const hi = this.box.max.getComponent(i);
      const at = lo + share * (hi - lo);
      let side = this.camera.position.getComponent(i) > at ? -1 : 1;
      if (flip) side = -side;
      const n = new THREE.Vector3();
      n.setComponent(i, side);
      // Keeps the points with n·p + c ≥ 0: side·p_i ≥ side·at.
      this.section.set(n, -side * at);
    }
    this.invalidate();
  }

  /** The burr's shape: profile (ρ, z) mm from tip to top, z toward the handle, and the shaft. */
  setTool(profileMm, shaftRadiusMm, shaftLengthMm) {
    const points = profileMm.map(([rho, z]) => new THREE.Vector2(Math.max(rho, 0), z));
    this.burr.geometry.dispose();
    // LatheGeometry turns about y: the tool group's y is the tool axis.
    this.burr.geometry = new THREE.LatheGeometry(points, 32);
    this.shaft.visible = shaftLengthMm > 0 && shaftRadiusMm > 0;
    if (this.shaft.visible) {
      this.shaft.geometry.dispose();
      this.shaft.geometry = new THREE.CylinderGeometry(shaftRadiusMm, shaftRadiusMm, shaftLengthMm, 24);
      this.shaft.position.set(0, shaftLengthMm / 2, 0);
    }
    this.invalidate();
  }

  /** The latest pose and force: centre (mm), axis (unit, burr → handle), force (N, server frame). */
  setPose(centreMm, axis, forceN) {
    this.posed = true;
    this.tool.visible = this.showTool;
    this.tool.position.set(...centreMm);
    const a = new THREE.Vector3(...axis);
    if (a.lengthSq() > 0) this.tool.quaternion.setFromUnitVectors(new THREE.Vector3(0, 1, 0), a.normalize());
    const f = forceN ? new THREE.Vector3(...forceN) : null;
    const magnitude = f ? f.length() : 0;
    this.arrow.visible = this.showTool && magnitude > 1e-3;
    if (this.arrow.visible) {
      const length = Math.max(1.5, magnitude * ARROW_MM_PER_N);
      this.arrow.position.set(...centreMm);
      this.arrow.setDirection(f.normalize());
      this.arrow.setLength(length, Math.min(1.2, length * 0.3), Math.min(0.8, length * 0.2));
    }
    this.invalidate();
  }

  /** Shows or hides the burr, its shaft and the force arrow. */
  setToolShown(shown) {
    this.showTool = shown;
    this.tool.visible = shown && Boolean(this.posed);
    if (!shown) this.arrow.visible = false;
    this.invalidate();
  }

  hideTool() {
    this.posed = false;
    this.tool.visible = false;
    this.arrow.visible = false;
    this.invalidate();
  }
}
