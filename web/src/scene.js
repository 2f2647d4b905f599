// Reads the viewer's binary scene (service/viewer/scene.py writes it): magic "PGSV", uint32 version, uint32 header
// length, the JSON header, then typed arrays at 4-byte aligned offsets, mapped without copying.
const MAGIC = "PGSV";
const VERSION = 1;
const TYPES = { float32: Float32Array, uint8: Uint8Array, int16: Int16Array, int32: Int32Array };

export function parseScene(buffer) {
  const bytes = new Uint8Array(buffer);
  const magic = String.fromCharCode(...bytes.subarray(0, 4));
  if (magic !== MAGIC) throw new Error(`not a panogs scene (starts with "${magic}", expected "${MAGIC}")`);
  const view = new DataView(buffer);
  const version = view.getUint32(4, true);
  if (version !== VERSION) throw new Error(`scene format version ${version}; this viewer reads ${VERSION}`);
  const length = view.getUint32(8, true);
  const header = JSON.parse(new TextDecoder().decode(bytes.subarray(12, 12 + length)));
  const body = 12 + length;
  const arrays = {};
  for (const [name, spec] of Object.entries(header.arrays)) {
    const Type = TYPES[spec.dtype];
    if (!Type) throw new Error(`array ${name}: unknown dtype ${spec.dtype}`);
    const count = spec.shape.reduce((a, b) => a * b, 1);
    arrays[name] = new Type(buffer, body + spec.offset, count);
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
