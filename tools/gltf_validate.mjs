// Validates glTF files with the Khronos glTF-Validator (npm package `gltf-validator`) and
// prints its counts per file; exits 1 when any file has an error or a warning (infos and hints
// are printed, not failures), 2 on a usage problem.
//
//   node tools/gltf_validate.mjs FILE.glb|FILE.gltf...
//
// GLTF_VALIDATOR_DIR (default: the working directory) must hold node_modules/gltf-validator;
// tools/gltf_check.sh installs it into target/node.
import { readFile } from "node:fs/promises";
import { createRequire } from "node:module";
import path from "node:path";

const base = process.env.GLTF_VALIDATOR_DIR ?? process.cwd();
const require = createRequire(path.join(path.resolve(base), "noop.js"));
const validator = require("gltf-validator");

const files = process.argv.slice(2);
if (files.length === 0) {
    console.error("usage: node tools/gltf_validate.mjs FILE.glb|FILE.gltf...");
    process.exit(2);
}
let bad = 0;
for (const file of files) {
    const data = new Uint8Array(await readFile(file));
    const report = await validator.validateBytes(data, {
        uri: file,
        // A .gltf here embeds its buffer; any external reference is a failure.
        externalResourceFunction: (uri) => Promise.reject(new Error(`external resource ${uri}`)),
        maxIssues: 0,
    });
    const i = report.issues;
    console.log(
        `${file}: ${i.numErrors} errors, ${i.numWarnings} warnings, ${i.numInfos} infos, ` +
            `${i.numHints} hints (glTF-Validator ${report.validatorVersion}; ` +
            `${report.info?.animationCount ?? 0} animation, ${report.info?.totalVertexCount ?? 0} vertices)`,
    );
    for (const m of i.messages) {
        console.log(`  [${["error", "warning", "info", "hint"][m.severity]}] ${m.code} ${m.pointer ?? ""}: ${m.message}`);
    }
    if (i.numErrors > 0 || i.numWarnings > 0) bad++;
}
process.exit(bad > 0 ? 1 : 0);
