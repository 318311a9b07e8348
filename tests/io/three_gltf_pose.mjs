// Load a .glb/.gltf with three.js's GLTFLoader (npm package three), play one animation, and
// print the skinned world positions of every vertex of one mesh at the given time as JSON:
// {"clips": [[name, duration_s, tracks]...], "vertices": [[x, y, z]...]}.
// Usage, from the repository root after `npm ci`:
//   node tests/io/three_gltf_pose.mjs FILE ANIMATION TIME_S MESH   (MESH: character or ghost)
import fs from "fs";
import { AnimationMixer, Vector3 } from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";

const [file, animation, time, meshName] = process.argv.slice(2);
const bytes = fs.readFileSync(file);
const data = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
new GLTFLoader().parse(data, "", (gltf) => {
  const clip = gltf.animations.find((a) => a.name === animation);
  const mixer = new AnimationMixer(gltf.scene);
  mixer.clipAction(clip).play();
  mixer.setTime(Number(time));
  gltf.scene.updateMatrixWorld(true);
  let mesh = null;  // a multi-primitive mesh loads as a group of skinned meshes sharing the vertices
  gltf.scene.traverse((o) => { if (!mesh && o.isSkinnedMesh && o.name.startsWith(meshName)) mesh = o; });
  mesh.skeleton.update();
  const v = new Vector3();
  const out = [];
  for (let i = 0; i < mesh.geometry.attributes.position.count; i++) {
    mesh.getVertexPosition(i, v);
    v.applyMatrix4(mesh.matrixWorld);
    out.push([v.x, v.y, v.z]);
  }
  console.log(JSON.stringify({ clips: gltf.animations.map((a) => [a.name, a.duration, a.tracks.length]),
                               vertices: out }));
}, (e) => { console.error(String(e)); process.exit(1); });
