// Validate .glb/.gltf files with the Khronos glTF validator (npm package gltf-validator) and
// print one JSON report per file: {"file", "numErrors", "numWarnings", "numInfos", "numHints",
// "messages"} (messages: the first issues, code + severity + message + pointer).
// Usage, from the repository root after `npm ci`:  node tests/io/validate_gltf.cjs run.glb [...]
// Exit status: 0 when no file has errors, 1 otherwise, 2 on bad usage or an unreadable file.
"use strict";
const fs = require("fs");
const path = require("path");
const validator = require("gltf-validator");

async function validate(file) {
  const bytes = new Uint8Array(fs.readFileSync(file));
  const report = await validator.validateBytes(bytes, {
    uri: path.basename(file),
    maxIssues: 100,
    externalResourceFunction: (uri) =>
      Promise.reject(new Error(`external resource ${uri} not allowed: buffers are embedded`)),
  });
  const issues = report.issues;
  return {
    file,
    numErrors: issues.numErrors,
    numWarnings: issues.numWarnings,
    numInfos: issues.numInfos,
    numHints: issues.numHints,
    messages: issues.messages.map((m) => ({ code: m.code, severity: m.severity, message: m.message,
                                             pointer: m.pointer })),
    info: report.info,
  };
}

async function main(files) {
  if (files.length === 0) {
    console.error("usage: node tests/io/validate_gltf.cjs FILE.glb [FILE.gltf ...]");
    return 2;
  }
  let status = 0;
  for (const file of files) {
    try {
      const r = await validate(file);
      console.log(JSON.stringify(r));
      if (r.numErrors > 0) status = Math.max(status, 1);
    } catch (e) {
      console.error(`${file}: ${e.message || e}`);
      status = 2;
    }
  }
  return status;
}

main(process.argv.slice(2)).then((code) => process.exit(code));
