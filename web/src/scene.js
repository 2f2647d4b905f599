// Reads the viewer's binary scene (service/viewer/scene.py writes it; the format is docs/viewer_format.md): magic
// "PGSV", uint32 version, uint32 header length, the JSON header, then typed arrays at 4-byte aligned offsets,
// mapped without copying. A short or garbled file fails here with a message that says what is wrong, not later in
// three.js. No DOM: `node --test` runs it.
const MAGIC = "PGSV";
const VERSION = 1;
const PREAMBLE = 12; // magic, version, header length
const TYPES = { float32: Float32Array, uint8: Uint8Array, int16: Int16Array, int32: Int32Array };
// The arrays the viewer draws: dtype and values per primitive.
const REQUIRED = {
  position: ["float32", 3],
  color: ["uint8", 3],
  semantic: ["int16", 1],
  instance: ["int32", 1],
  scale: ["float32", 1],
};

function fail(message) {
  throw new Error(`not a readable panogs scene: ${message}`);
}

function readHeader(buffer) {
  const bytes = new Uint8Array(buffer);
  const magic = String.fromCharCode(...bytes.subarray(0, 4));
  // A short file that starts like a scene is a cut download, not some other file.
  if (!MAGIC.startsWith(magic)) throw new Error(`not a panogs scene (starts with "${magic}", expected "${MAGIC}")`);
  if (buffer.byteLength < PREAMBLE)
    fail(`${buffer.byteLength} bytes, shorter than the ${PREAMBLE}-byte preamble (truncated)`);
  const view = new DataView(buffer);
  const version = view.getUint32(4, true);
  if (version !== VERSION) throw new Error(`scene format version ${version}; this viewer reads ${VERSION}`);
  const length = view.getUint32(8, true);
  const body = PREAMBLE + length;
  if (body > buffer.byteLength) fail(`the header ends at byte ${body}, the file at ${buffer.byteLength} (truncated)`);
  let header;
  try {
    header = JSON.parse(new TextDecoder().decode(bytes.subarray(PREAMBLE, body)));
  } catch (err) {
    fail(`the header is not JSON (${err.message})`);
  }
  if (!header || typeof header !== "object" || !header.arrays || typeof header.arrays !== "object") {
    fail("the header has no arrays");
  }
  if (!Number.isInteger(header.count) || header.count < 0) fail(`the header's count is ${header.count}`);
  return { header, body };
}

function mapArray(buffer, body, name, spec) {
  const Type = TYPES[spec.dtype];
  if (!Type) fail(`array ${name}: unknown dtype ${spec.dtype}`);
  if (!Array.isArray(spec.shape) || !spec.shape.every((d) => Number.isInteger(d) && d >= 0)) {
    fail(`array ${name}: shape ${JSON.stringify(spec.shape)}`);
  }
  const start = body + spec.offset;
  if (!Number.isInteger(spec.offset) || spec.offset < 0 || start % Type.BYTES_PER_ELEMENT !== 0) {
    fail(`array ${name}: offset ${spec.offset} is not a multiple of ${Type.BYTES_PER_ELEMENT}`);
  }
  const count = spec.shape.reduce((a, b) => a * b, 1);
  const end = start + count * Type.BYTES_PER_ELEMENT;
  if (end > buffer.byteLength) fail(`array ${name} ends at byte ${end}, the file at ${buffer.byteLength} (truncated)`);
  return new Type(buffer, start, count);
}

// buffer: an ArrayBuffer holding the whole file. Returns { header, position, color, semantic, instance, scale }.
export function parseScene(buffer) {
  const { header, body } = readHeader(buffer);
  const arrays = {};
  for (const [name, spec] of Object.entries(header.arrays)) arrays[name] = mapArray(buffer, body, name, spec);
  for (const [name, [dtype, width]] of Object.entries(REQUIRED)) {
    const array = arrays[name];
    if (!array) fail(`array ${name} is missing`);
    if (header.arrays[name].dtype !== dtype) fail(`array ${name} is ${header.arrays[name].dtype}, not ${dtype}`);
    if (array.length !== header.count * width) {
      fail(
        `array ${name} has ${array.length} values for ${header.count} primitives (expected ${header.count * width})`,
      );
    }
  }
  return { header, ...arrays };
}

// Fetches a scene with progress: onProgress(received, total) as bytes arrive (total 0 when the server did not say).
export async function fetchScene(url, onProgress, init = {}) {
  const response = await fetch(url, { credentials: "same-origin", ...init });
  if (!response.ok) {
    let message = `${response.status} ${response.statusText}`;
    try {
      message = (await response.json()).message || message;
    } catch (_) {
      /* not JSON: keep the status line */
    }
    throw new Error(message);
  }
  const total = Number(response.headers.get("Content-Length")) || 0;
  const reader = response.body.getReader();
  const chunks = [];
  let received = 0;
  for (;;) {
    const { done, value } = await reader.read();
    if (done) break;
    chunks.push(value);
    received += value.length;
    onProgress(received, total);
  }
  const buffer = new Uint8Array(received);
  let at = 0;
  for (const chunk of chunks) {
    buffer.set(chunk, at);
    at += chunk.length;
  }
  return parseScene(buffer.buffer);
}

// Decodes base64 (the offline file's inline scene) into an ArrayBuffer.
export function base64ToBuffer(text) {
  const binary = atob(text);
  const bytes = new Uint8Array(binary.length);
  for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
  return bytes.buffer;
}
