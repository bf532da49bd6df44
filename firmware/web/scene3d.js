// 3-D view (three.js): the cameras as frusta from the active parameter set, the live marker
// with the tool's axes (6-DOF), every tool's axes and name, the loose single LEDs with their
// ids, a fading trail, the robot's safety workspace box and the world/robot frame when the rig
// is registered. Tool and loose-LED names are HTML labels over the canvas, laid out each
// frame so that they never cover each other. Units are millimetres. The scene is drawn in
// the frame the positions arrive in: the world (robot) frame when registered, else camera 0's.

import * as THREE from "three";
import { OrbitControls } from "/web/vendor/three/OrbitControls.js";
import { TOOL_COLORS } from "./cameras.js";

const TRAIL_POINTS = 180; // six seconds at 30 records per second
const FRUSTUM_DEPTH_MM = 180;
const BG = new THREE.Color(0x0d0f13);
const LOOSE_COLOR = "#e6e6e6";
/** Screen gap kept between two name labels, px. */
const LABEL_GAP_PX = 2;

/** 4×4 matrix of a RigidTransform {r_row_major, t_mm}. */
function matrixOf(tf) {
  const r = tf.r_row_major;
  const t = tf.t_mm;
  return new THREE.Matrix4().set(r[0], r[1], r[2], t[0], r[3], r[4], r[5], t[1], r[6], r[7], r[8], t[2], 0, 0, 0, 1);
}

function label(text, color) {
  const c = document.createElement("canvas");
  c.width = 256;
  c.height = 64;
  const g = c.getContext("2d");
  g.font = "bold 36px system-ui, sans-serif";
  g.fillStyle = color;
  g.textBaseline = "middle";
  g.fillText(text, 8, 32);
  const tex = new THREE.CanvasTexture(c);
  tex.colorSpace = THREE.SRGBColorSpace;
  const s = new THREE.Sprite(new THREE.SpriteMaterial({ map: tex, depthTest: false, transparent: true }));
  s.scale.set(120, 30, 1);
  s.center.set(0, 0.5);
  return s;
}

export class Scene3D {
  constructor(container, info, frameLabel) {
    this.container = container;
    this.info = info;
    this.frameLabel = frameLabel;
    this.ok = false;
    this.dirty = true;
    this.rig = null; // {rig_id, cameras} of the last scene
    this.worldFrame = false;
    this.records = 0;
    this.workspace = null;
    try {
      this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    } catch (e) {
      info.textContent = `The 3-D view needs WebGL, which this browser did not provide (${e.message || e}).`;
      return;
    }
    this.ok = true;
    this.labelLayer = document.createElement("div");
    this.labelLayer.className = "scene-labels";
    if (getComputedStyle(container).position === "static") container.style.position = "relative";
    this.renderer.setPixelRatio(Math.min(2, window.devicePixelRatio || 1));
    container.append(this.renderer.domElement, this.labelLayer);
    this.scene = new THREE.Scene();
    this.scene.background = BG;
    this.camera = new THREE.PerspectiveCamera(45, 4 / 3, 5, 50000);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => (this.dirty = true));

    this.rigGroup = new THREE.Group(); // cameras, in the display frame
    this.scene.add(this.rigGroup);
    this.frameAxes = new THREE.AxesHelper(150);
    this.scene.add(this.frameAxes);
    this.frameText = label("cam 0 frame", "#9aa3b2");
    this.frameText.position.set(160, 0, 0); // at the tip of the X axis, clear of the camera 0 label
    this.scene.add(this.frameText);
    this.grid = new THREE.GridHelper(2000, 20, 0x3a4150, 0x262b34);
    this.grid.rotation.x = Math.PI / 2; // into the world's XY plane (Z up)
    this.grid.visible = false;
    this.scene.add(this.grid);

    this.marker = new THREE.Mesh(new THREE.SphereGeometry(9, 20, 14), new THREE.MeshBasicMaterial({ color: 0x3ecf6e }));
    this.marker.visible = false;
    this.scene.add(this.marker);
    this.toolAxes = new THREE.AxesHelper(70);
    this.toolAxes.visible = false;
    this.scene.add(this.toolAxes);

    this.trailPos = new Float32Array(TRAIL_POINTS * 3);
    this.trailCol = new Float32Array(TRAIL_POINTS * 3);
    this.trailN = 0;
    const tg = new THREE.BufferGeometry();
    tg.setAttribute("position", new THREE.BufferAttribute(this.trailPos, 3));
    tg.setAttribute("color", new THREE.BufferAttribute(this.trailCol, 3));
    tg.setDrawRange(0, 0);
    this.trail = new THREE.Line(tg, new THREE.LineBasicMaterial({ vertexColors: true }));
    this.trail.frustumCulled = false;
    this.scene.add(this.trail);

    this.workspaceBox = new THREE.Box3Helper(new THREE.Box3(), 0xffb347);
    this.workspaceBox.visible = false;
    this.scene.add(this.workspaceBox);

    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
    this.resetView();
    const loop = () => {
      if (this.dirty) {
        this.dirty = false;
        this.renderer.render(this.scene, this.camera);
        this.layoutLabels();
      }
      requestAnimationFrame(loop);
    };
    requestAnimationFrame(loop);
    this.describe();
  }

  resize() {
    const w = Math.max(100, this.container.clientWidth);
    const h = Math.max(80, this.container.clientHeight);
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.dirty = true;
  }

  /** Cameras as frusta and the workspace box from `GET /api/scene` (docs/http-api.md). */
  setScene(sc) {
    if (!this.ok || !sc) return;
    const cams = Array.isArray(sc.cameras) ? sc.cameras : [];
    this.rigGroup.clear();
    this.rig = cams.length ? { rig_id: sc.rig_id, cameras: cams } : null;
    const worldFromCam0 = sc.world_from_cam0 ? matrixOf(sc.world_from_cam0) : new THREE.Matrix4();
    cams.forEach((cam, n) => {
      const i = cam.camera ?? n;
      const d = FRUSTUM_DEPTH_MM;
      const corners = [
        [0, 0],
        [cam.width_px, 0],
        [cam.width_px, cam.height_px],
        [0, cam.height_px],
      ].map(([u, v]) => new THREE.Vector3(((u - cam.cx_px) / cam.fx_px) * d, ((v - cam.cy_px) / cam.fy_px) * d, d));
      const pts = [];
      for (const c of corners) pts.push(new THREE.Vector3(), c);
      for (let j = 0; j < 4; j++) pts.push(corners[j], corners[(j + 1) % 4]);
      // A tick on the image's top edge shows which way is up in the camera picture.
      const top = corners[0].clone().lerp(corners[1], 0.5);
      pts.push(top, top.clone().add(new THREE.Vector3(0, -d * 0.15, 0)));
      const color = i === 0 ? 0x5fb3ff : 0xc792ea;
      const lines = new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(pts), new THREE.LineBasicMaterial({ color }));
      // cam_from_cam0 maps camera-0 coordinates into this camera; its inverse places the camera.
      const camFromCam0 = matrixOf({ r_row_major: cam.r_cam_from_cam0_row_major, t_mm: cam.t_cam_from_cam0_mm });
      const m = worldFromCam0.clone().multiply(camFromCam0.invert());
      lines.applyMatrix4(m);
      this.rigGroup.add(lines);
      const t = label(`camera ${i}`, i === 0 ? "#5fb3ff" : "#c792ea");
      t.position.copy(new THREE.Vector3(0, 0, 0).applyMatrix4(m));
      this.rigGroup.add(t);
    });
    this.setWorld(!!sc.world_from_cam0);
    const ws = sc.workspace_mm;
    this.workspace = ws && ws.min && ws.max ? [ws.min, ws.max] : null;
    if (this.workspace) {
      this.workspaceBox.box.min.set(...ws.min);
      this.workspaceBox.box.max.set(...ws.max);
    }
    // The box is given in the frame the robot targets use, which is the frame drawn here.
    this.workspaceBox.visible = !!this.workspace;
    this.resetView();
    this.describe();
  }

  setWorld(world) {
    this.worldFrame = world;
    this.grid.visible = world;
    this.frameText.material.map.dispose();
    const t = label(world ? "world / robot frame" : "camera 0 frame", "#9aa3b2");
    this.frameText.material = t.material;
    this.frameLabel.textContent = world ? "frame: world (robot), Z up" : "frame: camera 0 (X right, Y down, Z forward)";
    this.camera.up.set(0, world ? 0 : -1, world ? 1 : 0);
    this.dirty = true;
  }

  /**
   * Every tool of the set (records with tool_id and tool name): axes and name per tool at its
   * pose; untracked tools are hidden. The main record's marker stays the robot's tool.
   */
  tools(list) {
    if (!this.ok) return;
    this.toolViews = this.toolViews || new Map();
    for (const t of list) {
      let v = this.toolViews.get(t.tool_id);
      if (!v || v.name !== t.tool) {
        if (v) this.scene.remove(v.group);
        const color = TOOL_COLORS[t.tool_id % TOOL_COLORS.length];
        if (v) v.label.remove();
        const group = new THREE.Group();
        group.add(new THREE.AxesHelper(90));
        this.scene.add(group);
        v = { name: t.tool, group, label: this.htmlLabel(t.tool, color, "tool"), tracked: false };
        this.toolViews.set(t.tool_id, v);
      }
      const p = t.position_mm;
      const q = t.orientation_wxyz;
      v.tracked = !!(p && q);
      v.group.visible = v.tracked;
      if (v.tracked) {
        v.group.position.set(p[0], p[1], p[2]);
        v.group.quaternion.set(q[1], q[2], q[3], q[0]);
      }
    }
    if (list.length) {
      // The robot tool's own axes would double one of these.
      this.toolAxes.visible = false;
      this.dirty = true;
    }
  }

  /** A name label over the canvas (placed by `layoutLabels`). */
  htmlLabel(text, color, kind) {
    const e = document.createElement("span");
    e.className = `scene-label ${kind}`;
    e.textContent = text;
    e.style.color = color;
    e.hidden = true;
    this.labelLayer.append(e);
    return e;
  }

  /**
   * The loose single LEDs of the set (records with loose_id): a small sphere and "loose N" per
   * LED; LEDs not in this set are hidden (a reacquired LED comes back under a new id).
   */
  loose(list) {
    if (!this.ok) return;
    this.looseViews = this.looseViews || new Map();
    const seen = new Set();
    for (const l of list) {
      const p = l.position_mm;
      if (!p) continue;
      seen.add(l.loose_id);
      let v = this.looseViews.get(l.loose_id);
      if (!v) {
        const dot = new THREE.Mesh(new THREE.SphereGeometry(6, 14, 10), new THREE.MeshBasicMaterial({ color: LOOSE_COLOR }));
        this.scene.add(dot);
        v = { id: l.loose_id, dot, label: this.htmlLabel(`loose ${l.loose_id}`, LOOSE_COLOR, "loose") };
        this.looseViews.set(l.loose_id, v);
      }
      v.dot.position.set(p[0], p[1], p[2]);
      v.dot.visible = true;
      v.position = p;
    }
    for (const [id, v] of this.looseViews) {
      if (seen.has(id)) continue;
      // Gone: ids are not reused, so the view is dropped.
      this.scene.remove(v.dot);
      v.dot.geometry.dispose();
      v.label.remove();
      this.looseViews.delete(id);
    }
    this.dirty = true;
  }

  /** The loose LEDs shown in 3-D (for the browser test): id, position and label text. */
  looseSummary() {
    return this.looseViews
      ? Array.from(this.looseViews.values()).map((v) => ({ id: v.id, position_mm: v.position, label: v.label.textContent, shown: !v.label.hidden }))
      : [];
  }

  /**
   * Places the name labels next to their 3-D anchors, then moves a label that would cover an
   * earlier one below it (top to bottom, left to right), so three tools crossing stay readable.
   */
  layoutLabels() {
    const w = this.renderer.domElement.clientWidth;
    const h = this.renderer.domElement.clientHeight;
    const items = [];
    const add = (label, pos, visible) => {
      if (!visible) {
        label.hidden = true;
        return;
      }
      const v = pos.clone().project(this.camera);
      const inside = v.z < 1 && Math.abs(v.x) <= 1.05 && Math.abs(v.y) <= 1.05;
      label.hidden = !inside;
      if (inside) items.push({ label, x: ((v.x + 1) / 2) * w + 8, y: ((1 - v.y) / 2) * h - 8 });
    };
    for (const v of this.toolViews ? this.toolViews.values() : []) add(v.label, v.group.position, v.tracked);
    for (const v of this.looseViews ? this.looseViews.values() : []) add(v.label, v.dot.position, v.dot.visible);
    items.sort((a, b) => a.y - b.y || a.x - b.x);
    const placed = [];
    for (const it of items) {
      const bw = it.label.offsetWidth || 60;
      const bh = it.label.offsetHeight || 16;
      let y = it.y;
      for (let moved = true; moved; ) {
        moved = false;
        for (const r of placed) {
          if (it.x < r.x + r.w + LABEL_GAP_PX && it.x + bw + LABEL_GAP_PX > r.x && y < r.y + r.h + LABEL_GAP_PX && y + bh + LABEL_GAP_PX > r.y) {
            y = r.y + r.h + LABEL_GAP_PX;
            moved = true;
          }
        }
      }
      placed.push({ x: it.x, y, w: bw, h: bh });
      it.label.style.transform = `translate(${Math.round(it.x)}px, ${Math.round(y)}px)`;
    }
  }

  /** Screen boxes of the shown name labels (for the browser test: none may overlap). */
  labelBoxes() {
    return Array.from(this.labelLayer.children)
      .filter((e) => !e.hidden)
      .map((e) => {
        const r = e.getBoundingClientRect();
        return { text: e.textContent, x: r.x, y: r.y, w: r.width, h: r.height };
      });
  }

  /** The tools shown in 3-D (for the browser test): name and whether tracked. */
  toolSummary() {
    return this.toolViews ? Array.from(this.toolViews.values()).map((v) => ({ name: v.name, tracked: v.tracked })) : [];
  }

  /** One position record from the live stream. */
  position(rec) {
    if (!this.ok || !rec) return;
    this.records += 1;
    if (rec.world_frame !== undefined && !!rec.world_frame !== this.worldFrame) this.setWorld(!!rec.world_frame);
    const p = rec.position_mm;
    if (!p) {
      this.marker.material.color.set(0xff5a5a);
      this.lastStatus = rec.status;
      this.dirty = true;
      this.describe();
      return;
    }
    this.lastStatus = rec.status;
    this.marker.material.color.set(0x3ecf6e);
    this.marker.visible = true;
    this.marker.position.set(p[0], p[1], p[2]);
    const q = rec.orientation_wxyz;
    this.toolAxes.visible = !!q;
    if (q) {
      this.toolAxes.position.copy(this.marker.position);
      this.toolAxes.quaternion.set(q[1], q[2], q[3], q[0]);
    }
    // Trail: shift by one (a few kB; records arrive at most 30 times a second).
    const n = Math.min(this.trailN + 1, TRAIL_POINTS);
    this.trailPos.copyWithin(0, 3);
    this.trailPos.set(p, (TRAIL_POINTS - 1) * 3);
    this.trailN = n;
    const start = TRAIL_POINTS - n;
    for (let i = 0; i < n; i++) {
      const a = (i + 1) / n; // older points fade into the background
      const c = BG.clone().lerp(new THREE.Color(0x3ecf6e), a);
      this.trailCol.set([c.r, c.g, c.b], (start + i) * 3);
    }
    const g = this.trail.geometry;
    g.setDrawRange(start, n);
    g.attributes.position.needsUpdate = true;
    g.attributes.color.needsUpdate = true;
    this.lastP = p;
    if (!this.framed) {
      this.framed = true;
      this.resetView();
    }
    this.dirty = true;
    this.describe();
  }

  describe() {
    if (!this.ok) return;
    const parts = [];
    if (this.rig) parts.push(`${this.rig.cameras.length} cameras of rig “${this.rig.rig_id}”`);
    else parts.push("camera frusta appear once the board sends the active parameter set");
    if (this.lastP) parts.push(`marker at (${this.lastP.map((v) => v.toFixed(1)).join(", ")}) mm`);
    if (this.lastStatus && this.lastStatus !== "ok") parts.push(`last record: ${this.lastStatus}`);
    if (this.workspace) parts.push("orange box: the robot's safety workspace");
    this.info.textContent = parts.join(" · ");
  }

  /** Frames the cameras and the marker. */
  resetView() {
    if (!this.ok) return;
    const box = new THREE.Box3();
    box.expandByPoint(new THREE.Vector3());
    this.rigGroup.children.forEach((o) => box.expandByObject(o));
    if (this.marker.visible) box.expandByPoint(this.marker.position);
    if (this.workspaceBox.visible) box.union(this.workspaceBox.box);
    const centre = box.getCenter(new THREE.Vector3());
    const radius = Math.max(300, box.getSize(new THREE.Vector3()).length() / 2);
    // Look from behind and above the cameras (camera frame: -Z is behind, -Y is up).
    const dir = this.worldFrame ? new THREE.Vector3(-1, -1.3, 0.9) : new THREE.Vector3(0.9, -1.1, -1.4);
    this.camera.position.copy(centre).add(dir.normalize().multiplyScalar(radius * 2.4));
    this.controls.target.copy(centre);
    this.controls.update();
    this.dirty = true;
  }
}
