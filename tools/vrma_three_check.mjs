// libflame's VRM Animation played by three-vrm: loads the avatar (VRMLoaderPlugin) and the .vrma
// (VRMAnimationLoaderPlugin), makes the clip with createVRMAnimationClip, samples it with an
// AnimationMixer at frame times, and compares every animated humanoid bone's normalized local
// rotation (vrm.humanoid.getNormalizedBoneNode(bone).quaternion) with libflame's expected ones
// (its own retarget of the same motion onto the avatar, in three-vrm's normalized space:
// written by the ignored test write_vrma_check_files in tests/retarget_files.rs). Quaternions are
// compared sign-insensitively, component by component, within 1e-4. Exits 1 on a difference.
//
//   node tools/vrma_three_check.mjs AVATAR.vrm MOTION.vrma EXPECTED.json
//
// THREE_VRM_DIR (default: the working directory) must hold node_modules with three,
// @pixiv/three-vrm and @pixiv/three-vrm-animation; tools/vrma_check.sh installs them into
// target/node.
import { readFile } from "node:fs/promises";
import path from "node:path";
import { pathToFileURL } from "node:url";

const base = path.resolve(process.env.THREE_VRM_DIR ?? process.cwd(), "node_modules");
const load = (p) => import(pathToFileURL(path.join(base, p)).href);
const THREE = await load("three/build/three.module.js");
const { GLTFLoader } = await load("three/examples/jsm/loaders/GLTFLoader.js");
const { VRMLoaderPlugin } = await load("@pixiv/three-vrm/lib/three-vrm.module.js");
const { VRMAnimationLoaderPlugin, createVRMAnimationClip } = await load(
    "@pixiv/three-vrm-animation/lib/three-vrm-animation.module.js",
);

const TOLERANCE = 1e-4;
const [avatarPath, vrmaPath, expectedPath] = process.argv.slice(2);
if (!expectedPath) {
    console.error("usage: node tools/vrma_three_check.mjs AVATAR.vrm MOTION.vrma EXPECTED.json");
    process.exit(2);
}

/** The glTF at `file` parsed by GLTFLoader with `plugin` (no DOM: the files have no textures). */
async function parse(file, plugin) {
    const bytes = await readFile(file);
    const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
    const loader = new GLTFLoader();
    loader.register(plugin);
    return new Promise((resolve, reject) => loader.parse(buffer, "", resolve, reject));
}

const vrm = (await parse(avatarPath, (p) => new VRMLoaderPlugin(p))).userData.vrm;
const vrmAnimation = (await parse(vrmaPath, (p) => new VRMAnimationLoaderPlugin(p))).userData
    .vrmAnimations[0];
if (!vrm || !vrmAnimation) {
    console.error("vrma_three_check: three-vrm did not find the VRM or the VRM Animation");
    process.exit(1);
}
const expected = JSON.parse(await readFile(expectedPath, "utf8"));
const clip = createVRMAnimationClip(vrmAnimation, vrm);
const mixer = new THREE.AnimationMixer(vrm.scene);
// Played once and held: a repeating action wraps the last frame's time (the clip's duration)
// back to 0.
const action = mixer.clipAction(clip);
action.setLoop(THREE.LoopOnce, 1);
action.clampWhenFinished = true;
action.play();

const bones = Object.keys(expected.bones);
const frames = [0, 1, 7, 13, 20, 29, expected.frames - 1].filter((f) => f < expected.frames);
let worst = 0;
let worstAt = "";
let missing = [];
for (const frame of frames) {
    mixer.setTime(frame / expected.fps);
    vrm.update(0);
    for (const bone of bones) {
        const node = vrm.humanoid.getNormalizedBoneNode(bone);
        if (!node) {
            missing.push(bone);
            continue;
        }
        const q = node.quaternion;
        const got = [q.x, q.y, q.z, q.w];
        const want = expected.bones[bone][frame];
        const same = Math.max(...got.map((v, k) => Math.abs(v - want[k])));
        const flip = Math.max(...got.map((v, k) => Math.abs(v + want[k])));
        const d = Math.min(same, flip);
        if (d > worst) {
            worst = d;
            worstAt = `${bone} at frame ${frame}: three-vrm ${got.map((v) => v.toFixed(6))}, libflame ${want.map((v) => v.toFixed(6))}`;
        }
    }
}
// Every bone the file animates must have been a track of the clip (three-vrm drops bones the
// avatar lacks; this avatar has all 22).
const tracks = clip.tracks.filter((t) => t.name.endsWith(".quaternion")).length;
console.log(
    `vrma_three_check: ${bones.length} bones x ${frames.length} frames, ${tracks} rotation tracks; ` +
        `worst sign-insensitive component difference ${worst.toExponential(3)} (tolerance ${TOLERANCE})`,
);
if (missing.length > 0) {
    console.error(`vrma_three_check: no normalized bone for ${[...new Set(missing)].join(", ")}`);
    process.exit(1);
}
if (tracks !== bones.length) {
    console.error(`vrma_three_check: ${tracks} rotation tracks for ${bones.length} bones`);
    process.exit(1);
}
if (!(worst <= TOLERANCE)) {
    console.error(`vrma_three_check: ${worstAt}`);
    process.exit(1);
}
