// Runs the Khronos glTF-Validator on each .glb given; fails on any error except the one pending spec change:
// MESH_PRIMITIVE_INVALID_ATTRIBUTE reported on a KHR_gaussian_splatting: attribute.
import { readFileSync } from 'node:fs';
import { basename } from 'node:path';
import validator from 'gltf-validator';

const IGNORED_CODE = 'MESH_PRIMITIVE_INVALID_ATTRIBUTE';
const IGNORED_PREFIX = 'KHR_gaussian_splatting:';

// The validator names the attribute in the pointer (/meshes/0/primitives/0/attributes/NAME) and the message.
function isPendingSpecChange(issue) {
  if (issue.code !== IGNORED_CODE) return false;
  const pointer = issue.pointer || '';
  const attribute = pointer.slice(pointer.lastIndexOf('/') + 1);
  return attribute.startsWith(IGNORED_PREFIX);
}

const files = process.argv.slice(2);
if (files.length === 0) {
  console.error('usage: node validate.mjs FILE.glb...');
  process.exit(2);
}
let failed = 0;
for (const file of files) {
  const report = await validator.validateBytes(new Uint8Array(readFileSync(file)), {
    uri: basename(file),
    maxIssues: 0,
  });
  const issues = report.issues.messages;
  const errors = issues.filter((m) => m.severity === 0);
  const ignored = errors.filter(isPendingSpecChange);
  const remaining = errors.filter((m) => !isPendingSpecChange(m));
  const counts = report.issues;
  console.log(`${file}: validator ${report.validatorVersion}: ${counts.numErrors} errors ` +
              `(${ignored.length} ignored ${IGNORED_CODE} on ${IGNORED_PREFIX}*), ${counts.numWarnings} warnings, ` +
              `${counts.numInfos} infos, ${counts.numHints} hints`);
  for (const m of issues.filter((m) => m.severity === 1 || m.severity === 2))
    console.log(`  ${m.severity === 1 ? 'warning' : 'info'} ${m.code} ${m.pointer || ''}: ${m.message}`);
  for (const m of remaining) console.log(`  ERROR ${m.code} ${m.pointer || ''}: ${m.message}`);
  if (remaining.length > 0) failed += 1;
}
console.log(failed === 0 ? 'validator: PASS' : `validator: FAIL (${failed} of ${files.length} files)`);
process.exit(failed === 0 ? 0 : 1);
