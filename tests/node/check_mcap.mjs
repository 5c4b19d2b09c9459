// An independent reader of autotune's run files, for tests/integration/test_mcap_node.py.
//
//   node check_mcap.mjs FILE.mcap [FILE.mcap ...]   → one JSON object on stdout
//   node check_mcap.mjs --schemas < {name: schema}   → {name: "ok" or the parser's error}
//
// Each file is read with the TypeScript MCAP reader (@mcap/core's indexed reader: summary,
// chunk and message indexes, CRCs); every channel's schema is parsed by Foxglove's own JSON
// Schema parser (parse_json_schema.js, Lichtblick's parseJsonSchema) and compiled by ajv for
// the draft the schema declares; every message is validated against its channel's schema,
// deserialised as Foxglove does (the parser's postprocessValue), and checked against the
// datatypes Foxglove derived (a number where Foxglove expects a number, and so on). Nothing
// is judged here: the Python test asserts on what this prints.

import { readFile } from "node:fs/promises";

import { McapIndexedReader } from "@mcap/core";
import Ajv2020 from "ajv/dist/2020.js";
import { decompress } from "fzstd";

import { parseJsonSchema } from "./parse_json_schema.js";

const DIALECTS = { "https://json-schema.org/draft/2020-12/schema": Ajv2020 };
const NUMERIC = new Set(["float64", "int32", "uint32", "uint8"]);

function readable(bytes) {
  return {
    size: async () => BigInt(bytes.byteLength),
    read: async (offset, length) => bytes.subarray(Number(offset), Number(offset + length)),
  };
}

// Where a value disagrees with the datatype Foxglove derived for it: "path: why", or none.
function mismatches(value, typeName, datatypes, path, out) {
  const fields = datatypes.get(typeName)?.definitions ?? [];
  for (const [name, v] of Object.entries(value)) {
    const f = fields.find((d) => d.name === name && !d.isConstant);
    if (f === undefined || v === null) continue; // a map's key, or a value Foxglove has no type for
    const at = `${path}.${name}`;
    const check = (x, where) => {
      if (f.isComplex) {
        if (typeof x !== "object" || x === null || Array.isArray(x)) out.push(`${where}: not an object`);
        else mismatches(x, f.type, datatypes, where, out);
      } else if (NUMERIC.has(f.type) && typeof x !== "number") out.push(`${where}: ${f.type}, got ${typeof x}`);
      else if (f.type === "string" && typeof x !== "string") out.push(`${where}: string, got ${typeof x}`);
      else if (f.type === "bool" && typeof x !== "boolean") out.push(`${where}: bool, got ${typeof x}`);
    };
    if (f.isArray) {
      if (!Array.isArray(v)) out.push(`${at}: not an array`);
      else v.forEach((x, i) => check(x, `${at}[${i}]`));
    } else check(v, at);
  }
  return out;
}

async function checkFile(path) {
  const bytes = new Uint8Array(await readFile(path));
  const reader = await McapIndexedReader.Initialize({
    readable: readable(bytes),
    decompressHandlers: { zstd: (data, size) => decompress(data, new Uint8Array(Number(size))) },
  });
  const schemas = {};
  const parsed = new Map(); // schema id → { validate, datatypes, postprocess }
  for (const [id, s] of reader.schemasById) {
    const info = (schemas[s.name] = { encoding: s.encoding });
    let schema;
    try {
      schema = JSON.parse(new TextDecoder().decode(s.data));
    } catch (err) {
      info.json = String(err);
      continue;
    }
    info.dialect = schema.$schema ?? null;
    try {
      const { datatypes, postprocessValue } = parseJsonSchema(schema, s.name);
      info.foxglove = "ok";
      info.numeric = [...(datatypes.get(s.name)?.definitions ?? [])]
        .filter((d) => NUMERIC.has(d.type) && !d.isArray)
        .map((d) => d.name);
      parsed.set(id, { datatypes, postprocess: postprocessValue });
    } catch (err) {
      info.foxglove = err.message;
      parsed.set(id, {});
    }
    const Ajv = DIALECTS[schema.$schema];
    if (Ajv === undefined) {
      info.ajv = `no validator for the dialect ${JSON.stringify(schema.$schema)}`;
      continue;
    }
    try {
      parsed.get(id).validate = new Ajv({ strict: true, allErrors: false }).compile(schema);
      info.ajv = "ok";
    } catch (err) {
      info.ajv = err.message;
    }
  }
  const channels = {};
  const errors = [];
  const times = []; // [topic, log time (ns, as text), the message's t]
  let messages = 0;
  let valid = 0;
  for await (const m of reader.readMessages({ validateCrcs: true })) {
    messages += 1;
    const ch = reader.channelsById.get(m.channelId);
    channels[ch.topic] = (channels[ch.topic] ?? 0) + 1;
    const where = `${ch.topic} #${m.sequence}`;
    let value;
    try {
      value = JSON.parse(new TextDecoder().decode(m.data));
    } catch (err) {
      errors.push(`${where}: not JSON: ${err.message}`);
      continue;
    }
    times.push([ch.topic, m.logTime.toString(), value.t ?? null]);
    const p = parsed.get(ch.schemaId) ?? {};
    if (p.validate === undefined) {
      errors.push(`${where}: no validator for its schema`);
    } else if (!p.validate(value)) {
      const e = p.validate.errors[0];
      errors.push(`${where}: ${e.instancePath || "/"} ${e.message}`);
    } else {
      valid += 1;
    }
    if (p.postprocess !== undefined) {
      const name = reader.schemasById.get(ch.schemaId).name;
      try {
        const out = p.postprocess(structuredClone(value));
        for (const why of mismatches(out, name, p.datatypes, name, [])) errors.push(`${where}: foxglove: ${why}`);
      } catch (err) {
        errors.push(`${where}: foxglove: ${err.message}`);
      }
    }
  }
  const metadata = {};
  for await (const md of reader.readMetadata()) metadata[md.name] = Object.fromEntries(md.metadata);
  const stats = reader.statistics;
  return {
    path,
    profile: reader.header.profile,
    statistics: stats
      ? {
          messages: Number(stats.messageCount),
          channels: stats.channelCount,
          schemas: stats.schemaCount,
          start: stats.messageStartTime.toString(),
          end: stats.messageEndTime.toString(),
        }
      : null,
    chunk_indexes: reader.chunkIndexes.length,
    messages,
    valid,
    channels,
    schemas,
    errors: errors.slice(0, 50),
    error_count: errors.length,
    times,
    metadata,
  };
}

// With --schemas: {name: schema} on stdin → {name: "ok" or Foxglove's parser's error}.
async function checkSchemas() {
  const chunks = [];
  for await (const chunk of process.stdin) chunks.push(chunk);
  const out = {};
  for (const [name, schema] of Object.entries(JSON.parse(Buffer.concat(chunks).toString()))) {
    try {
      parseJsonSchema(schema, name);
      out[name] = "ok";
    } catch (err) {
      out[name] = err.message;
    }
  }
  return out;
}

if (process.argv[2] === "--schemas") {
  process.stdout.write(JSON.stringify(await checkSchemas()));
} else {
  const files = [];
  for (const path of process.argv.slice(2)) files.push(await checkFile(path));
  process.stdout.write(JSON.stringify({ files }));
}
