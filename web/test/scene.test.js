// The binary scene parser against files built here from the documented layout (docs/viewer_format.md), written
// independently of service/viewer/scene.py: magic, little-endian version and header length, space-padded JSON,
// arrays at 4-byte aligned offsets from the body's start.
import assert from "node:assert/strict";
import { afterEach, describe, it } from "node:test";
import { base64ToBuffer, fetchScene, parseScene } from "../src/scene.js";

const pad4 = (n) => Math.ceil(n / 4) * 4;

// arrays: [name, dtype, shape, TypedArray]; order: the order of the bytes in the body (the header names offsets).
function encode(header, arrays, order = arrays.map(([name]) => name)) {
  const layout = {};
  let offset = 0;
  for (const name of order) {
    const [, dtype, shape, values] = arrays.find(([n]) => n === name);
    layout[name] = { dtype, shape, offset };
    offset += pad4(values.byteLength);
  }
  const json = new TextEncoder().encode(JSON.stringify({ ...header, arrays: layout }));
  const headerLength = pad4(json.length);
  const bytes = new Uint8Array(12 + headerLength + offset);
  bytes.set(new TextEncoder().encode("PGSV"), 0);
  const view = new DataView(bytes.buffer);
  view.setUint32(4, 1, true);
  view.setUint32(8, headerLength, true);
  bytes.set(json, 12);
  bytes.fill(0x20, 12 + json.length, 12 + headerLength); // spaces: still valid JSON
  for (const name of order) {
    const [, , , values] = arrays.find(([n]) => n === name);
    bytes.set(
      new Uint8Array(values.buffer, values.byteOffset, values.byteLength),
      12 + headerLength + layout[name].offset,
    );
  }
  return bytes.buffer;
}

const HEADER = {
  count: 3,
  total: 5,
  bounds: { min: [0, 0, 0], max: [1, 2, 3] },
  classes: [{ index: 0, name: "wall", kind: "stuff", color: [31, 119, 180], count: 2 }],
  void: { color: [128, 128, 128], count: 1 },
  instances: [{ id: 0, class_name: "wall", color: [10, 20, 30] }],
};

function arrays() {
  return [
    ["position", "float32", [3, 3], new Float32Array([0, 0, 0, 1, 2, 3, 0.5, 0.25, -1.5])],
    ["color", "uint8", [3, 3], new Uint8Array([1, 2, 3, 4, 5, 6, 7, 8, 9])], // 9 bytes: the next array is padded
    ["semantic", "int16", [3], new Int16Array([0, -1, 0])], // 6 bytes
    ["instance", "int32", [3], new Int32Array([0, -1, 0])],
    ["scale", "float32", [3], new Float32Array([0.01, 0.02, 0.04])],
  ];
}

function throwsMessage(fn, pattern) {
  assert.throws(fn, (err) => {
    assert.match(err.message, pattern);
    return true;
  });
}

describe("parseScene", () => {
  it("reads the header and maps every array with its dtype and values", () => {
    const buffer = encode(HEADER, arrays());
    const scene = parseScene(buffer);
    assert.deepEqual(scene.header.bounds, HEADER.bounds);
    assert.equal(scene.header.total, 5);
    assert.deepEqual(scene.header.arrays.color, { dtype: "uint8", shape: [3, 3], offset: 36 });
    for (const [name, , , values] of arrays()) {
      assert.equal(scene[name].constructor, values.constructor, name);
      assert.deepEqual([...scene[name]], [...values], name);
      assert.equal(scene[name].buffer, buffer, `${name} is a view on the file, not a copy`);
    }
  });

  it("follows the header's offsets, not the order of the arrays", () => {
    const order = ["scale", "semantic", "color", "instance", "position"];
    const scene = parseScene(encode(HEADER, arrays(), order));
    assert.deepEqual([...scene.semantic], [0, -1, 0]);
    assert.deepEqual([...scene.position.subarray(3, 6)], [1, 2, 3]);
    assert.ok(scene.header.arrays.position.offset > scene.header.arrays.scale.offset);
  });

  it("keeps extra header fields and extra arrays", () => {
    const extra = ["opacity", "float32", [3], new Float32Array([1, 0.5, 0])];
    const scene = parseScene(encode({ ...HEADER, title: "room" }, [...arrays(), extra]));
    assert.equal(scene.header.title, "room");
    assert.deepEqual([...scene.opacity], [1, 0.5, 0]);
  });

  it("refuses another file type by its first bytes", () => {
    throwsMessage(
      () => parseScene(new TextEncoder().encode('{"count": 3}').buffer),
      /not a panogs scene \(starts with "{"co", expected "PGSV"\)/,
    );
  });

  it("refuses another format version", () => {
    const buffer = encode(HEADER, arrays());
    new DataView(buffer).setUint32(4, 2, true);
    throwsMessage(() => parseScene(buffer), /format version 2; this viewer reads 1/);
  });

  it("names a file cut short, wherever the cut is", () => {
    const whole = encode(HEADER, arrays());
    const cut = (n) => whole.slice(0, n);
    throwsMessage(() => parseScene(cut(0)), /0 bytes, shorter than the 12-byte preamble \(truncated\)/);
    throwsMessage(() => parseScene(cut(6)), /6 bytes, shorter than the 12-byte preamble/);
    throwsMessage(() => parseScene(cut(40)), /the header ends at byte \d+, the file at 40 \(truncated\)/);
    throwsMessage(
      () => parseScene(cut(whole.byteLength - 1)),
      /array scale ends at byte \d+, the file at \d+ \(truncated\)/,
    );
  });

  it("names a garbled header", () => {
    const buffer = encode(HEADER, arrays());
    new Uint8Array(buffer)[12] = "]".charCodeAt(0);
    throwsMessage(() => parseScene(buffer), /the header is not JSON/);
  });

  it("refuses a misaligned offset, an unknown dtype, a missing or mis-sized array", () => {
    const spoil = (edit) => {
      const buffer = encode(HEADER, arrays());
      const length = new DataView(buffer).getUint32(8, true);
      const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 12, length)));
      edit(header);
      const json = new TextEncoder().encode(JSON.stringify(header));
      assert.ok(json.length <= length, "the edited header fits in place");
      const bytes = new Uint8Array(buffer);
      bytes.fill(0x20, 12, 12 + length);
      bytes.set(json, 12);
      return buffer;
    };
    throwsMessage(
      () => parseScene(spoil((h) => (h.arrays.scale.offset += 2))),
      /array scale: offset \d+ is not a multiple of 4/,
    );
    throwsMessage(
      () => parseScene(spoil((h) => (h.arrays.scale.dtype = "float64"))),
      /array scale: unknown dtype float64/,
    );
    throwsMessage(() => parseScene(spoil((h) => delete h.arrays.instance)), /array instance is missing/);
    throwsMessage(
      () => parseScene(spoil((h) => (h.arrays.scale.shape = [2]))),
      /array scale has 2 values for 3 primitives/,
    );
    throwsMessage(
      () => parseScene(spoil((h) => (h.arrays.semantic.dtype = "int32"))),
      /array semantic is int32, not int16/,
    );
    throwsMessage(() => parseScene(spoil((h) => delete h.arrays)), /the header has no arrays/);
  });
});

describe("base64ToBuffer", () => {
  it("decodes the offline file's inline scene", () => {
    const buffer = encode(HEADER, arrays());
    const text = Buffer.from(buffer).toString("base64");
    assert.deepEqual([...parseScene(base64ToBuffer(text)).instance], [0, -1, 0]);
  });
});

describe("fetchScene", () => {
  const realFetch = globalThis.fetch;
  afterEach(() => {
    globalThis.fetch = realFetch;
  });

  it("reports progress chunk by chunk and parses the whole", async () => {
    const bytes = new Uint8Array(encode(HEADER, arrays()));
    const half = 50;
    globalThis.fetch = async () =>
      new Response(
        new ReadableStream({
          start(controller) {
            controller.enqueue(bytes.slice(0, half));
            controller.enqueue(bytes.slice(half));
            controller.close();
          },
        }),
        { headers: { "Content-Length": String(bytes.length) } },
      );
    const progress = [];
    const scene = await fetchScene("scene.bin", (got, total) => progress.push([got, total]));
    assert.deepEqual(progress, [
      [half, bytes.length],
      [bytes.length, bytes.length],
    ]);
    assert.deepEqual([...scene.scale], [...arrays()[4][3]]);
  });

  it("raises the service's message when the answer is an error", async () => {
    globalThis.fetch = async () =>
      new Response(JSON.stringify({ message: "job 1 not found" }), { status: 404, statusText: "Not Found" });
    await assert.rejects(
      fetchScene("x", () => {}),
      /^Error: job 1 not found$/,
    );
    globalThis.fetch = async () => new Response("<html>", { status: 502, statusText: "Bad Gateway" });
    await assert.rejects(
      fetchScene("x", () => {}),
      /^Error: 502 Bad Gateway$/,
    );
  });
});
