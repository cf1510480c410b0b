// Builds ../static/viewer.js (the splat viewer, minified, one ES module) and ../static/viewer-license.txt (the
// bundled engine's licence). Run `npm ci && npm run build` here after changing src/ or package.json.
import { readFileSync, writeFileSync } from "node:fs";
import { build } from "esbuild";

const MAX_BYTES = 2 * 1024 * 1024; // no committed file may be larger
const engine = JSON.parse(readFileSync("node_modules/playcanvas/package.json", "utf8"));

await build({
  entryPoints: ["src/viewer.js"],
  bundle: true,
  format: "esm",
  minify: true,
  target: "es2022",
  legalComments: "none",
  banner: { js: `/* SymGS splat viewer; bundles PlayCanvas engine ${engine.version} (MIT, see viewer-license.txt) */` },
  outfile: "../static/viewer.js",
});

const notice = `The job page's splat viewer (viewer.js) bundles the PlayCanvas engine ${engine.version}
(npm package "playcanvas"), distributed under the following licence.

`;
writeFileSync("../static/viewer-license.txt", notice + readFileSync("node_modules/playcanvas/LICENSE", "utf8"));

const size = readFileSync("../static/viewer.js").length;
if (size > MAX_BYTES) throw new Error(`viewer.js is ${size} bytes, over the ${MAX_BYTES} byte limit`);
console.log(`viewer.js: ${size} bytes`);
