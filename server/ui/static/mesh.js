// Reader of the server's mesh-chunk messages (BFMC, proto/MESH.md section 3), and the copy of
// the carved surface it keeps current (section 4). No three.js here: plain typed arrays, so the
// parser can be checked on its own.

const MAGIC = 0x434d4642; // "BFMC" read little-endian
export const FLAG_MORE = 1;
export const FLAG_FULL = 2;

/**
 * Parse one message.
 * @param {ArrayBuffer} buffer
 * @returns {{version:number, flags:number, session:number, chunkCells:number,
 *            boneVersion:number, since:number, generation:number|null,
 *            chunks:Array<{key:string, index:number[], positions:Float32Array,
 *            normals:Float32Array, labels:Uint8Array, triangles:Uint32Array}>}}
 * Throws an Error saying what is wrong with a malformed message.
 */
export function parseMessage(buffer) {
  const view = new DataView(buffer);
  const need = (offset, bytes, what) => {
    if (offset + bytes > buffer.byteLength) {
      throw new Error(`mesh message truncated in ${what} (${buffer.byteLength} bytes)`);
    }
  };
  need(0, 40, "the header");
  if (view.getUint32(0, true) !== MAGIC) throw new Error("not a BFMC mesh message");
  const version = view.getUint16(4, true);
  if (version !== 1 && version !== 2) throw new Error(`unknown mesh format ${version}`);
  const header = version === 2 ? 48 : 40;
  need(0, header, "the header");
  const out = {
    version,
    flags: view.getUint16(6, true),
    session: view.getUint32(8, true),
    chunkCells: view.getUint32(12, true),
    // Versions stay far below 2^53: a Number is exact.
    boneVersion: Number(view.getBigUint64(16, true)),
    since: Number(view.getBigUint64(24, true)),
    generation: version === 2 ? Number(view.getBigUint64(40, true)) : null,
    chunks: [],
  };
  const count = view.getUint32(36, true);
  let at = header;
  for (let n = 0; n < count; n += 1) {
    need(at, 20, `chunk ${n}'s header`);
    const index = [view.getInt32(at, true), view.getInt32(at + 4, true),
      view.getInt32(at + 8, true)];
    const V = view.getUint32(at + 12, true);
    const T = view.getUint32(at + 16, true);
    const labelsEnd = 20 + 25 * V;
    const pad = (4 - (labelsEnd % 4)) % 4;
    const size = labelsEnd + pad + 12 * T;
    need(at, size, `chunk ${n}`);
    if (T === 0 && V !== 0) throw new Error(`chunk ${index} has vertices but no triangles`);
    // Copies: the message's buffer is dropped once applied, and a Float32Array view needs
    // 4-byte alignment, which every field has (offsets are multiples of 4 but the labels').
    const positions = new Float32Array(buffer.slice(at + 20, at + 20 + 12 * V));
    const normals = new Float32Array(buffer.slice(at + 20 + 12 * V, at + 20 + 24 * V));
    const labels = new Uint8Array(buffer.slice(at + 20 + 24 * V, at + labelsEnd));
    const triangles = new Uint32Array(buffer.slice(at + labelsEnd + pad, at + size));
    for (let i = 0; i < triangles.length; i += 1) {
      if (triangles[i] >= V) throw new Error(`chunk ${index}: vertex index out of range`);
    }
    out.chunks.push({ key: index.join(","), index, positions, normals, labels, triangles });
    at += size;
  }
  return out;
}

/**
 * The carved surface as the client holds it: chunk key → chunk, kept current by applying
 * messages in order (proto/MESH.md section 4). ``onChange(key, chunk|null)`` is called for
 * every chunk added, replaced (chunk) or removed (null); ``onClear()`` before a FULL update.
 */
export class ChunkCopy {
  constructor({ onChange, onClear }) {
    this.chunks = new Map();
    this.have = null;
    this.generation = null;
    this.low = null;
    this.onChange = onChange;
    this.onClear = onClear;
  }

  apply(message) {
    if (message.flags & FLAG_FULL) {
      this.chunks.clear();
      this.onClear();
    }
    for (const chunk of message.chunks) {
      if (chunk.triangles.length === 0) {
        if (this.chunks.delete(chunk.key)) this.onChange(chunk.key, null);
      } else {
        this.chunks.set(chunk.key, chunk);
        this.onChange(chunk.key, chunk);
      }
    }
    this.low = this.low === null ? message.boneVersion : Math.min(this.low, message.boneVersion);
    if (!(message.flags & FLAG_MORE)) {
      this.have = this.low;
      this.generation = message.generation;
      this.low = null;
    }
  }
}

/**
 * Triangles of a binary STL file (the server's mesh export): positions (9 floats per
 * triangle) and the facet normals repeated per vertex.
 * @param {ArrayBuffer} buffer
 * @returns {{positions: Float32Array, normals: Float32Array}}
 */
export function parseStl(buffer) {
  if (buffer.byteLength < 84) throw new Error("STL truncated in its header");
  const view = new DataView(buffer);
  const count = view.getUint32(80, true);
  if (84 + 50 * count !== buffer.byteLength) throw new Error(`STL of ${count} triangles has ${buffer.byteLength} bytes`);
  const positions = new Float32Array(9 * count);
  const normals = new Float32Array(9 * count);
  for (let t = 0; t < count; t += 1) {
    const at = 84 + 50 * t;
    for (let v = 0; v < 3; v += 1) {
      for (let c = 0; c < 3; c += 1) {
        normals[9 * t + 3 * v + c] = view.getFloat32(at + 4 * c, true);
        positions[9 * t + 3 * v + c] = view.getFloat32(at + 12 + 12 * v + 4 * c, true);
      }
    }
  }
  return { positions, normals };
}
