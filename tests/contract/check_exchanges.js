#!/usr/bin/env node
// Checks recorded HTTP exchanges with vsmd against the API contract (proto/openapi.yaml), and
// that they cover it. Run by contract_test.py (ctest contract.live); the exchanges are its
// recording of the real daemon's answers.
//
// For every exchange: the path matches a path of the contract, the method an operation of it,
// the status a response of that operation (the exact code, else `NXX`, else `default`); the
// Content-Type is one of that response's media types (no body where it has none); a JSON body
// (gunzipped when Content-Encoding says gzip) validates against the media type's schema, each
// event of a text/event-stream against the schema its name selects in the stream schema's
// `$defs`; documented headers that are present validate against their schemas (required ones
// must be present), and every response carries a valid X-Request-Id. Schemas are checked with
// Ajv's JSON Schema 2020-12 validator (OpenAPI 3.1's dialect) and ajv-formats, strict.
//
// Coverage: every (method, path, status) of the contract must be among the exchanges, except
// those listed in the exclusions file with a reason; an exclusion that names nothing in the
// contract, or that was exercised after all, is an error too (the list stays true).
//
// Two negative controls run on the recorded answers (an undocumented status, a body missing its
// required members); if either passes, the checker itself is broken and says so.
//
// Usage: check_exchanges.js --tools <contract-tools prefix> --contract <openapi.yaml>
//            --exchanges <exchanges.json> --exclusions <coverage-exclusions.txt>
'use strict';

const fs = require('fs');
const path = require('path');
const zlib = require('zlib');
const {createRequire} = require('module');

function args() {
  const out = {};
  const argv = process.argv.slice(2);
  for (let i = 0; i < argv.length; i += 2) {
    if (!argv[i].startsWith('--') || i + 1 >= argv.length) {
      throw new Error('usage: check_exchanges.js --tools DIR --contract YAML --exchanges JSON ' +
                      '--exclusions TXT');
    }
    out[argv[i].slice(2)] = argv[i + 1];
  }
  for (const name of ['tools', 'contract', 'exchanges', 'exclusions']) {
    if (!out[name]) throw new Error('--' + name + ' is required');
  }
  return out;
}

const opts = args();
const toolsRequire = createRequire(path.join(path.resolve(opts.tools), 'package.json'));
const Ajv2020 = toolsRequire('ajv/dist/2020');
const addFormats = toolsRequire('ajv-formats');
const YAML = toolsRequire('yaml');

const METHODS = ['get', 'put', 'post', 'delete', 'options', 'head', 'patch', 'trace'];
const contract = YAML.parse(fs.readFileSync(opts.contract, 'utf8'));
const exchanges = JSON.parse(fs.readFileSync(opts.exchanges, 'utf8'));

// ---- schemas ---------------------------------------------------------------------------------

const ajv = new Ajv2020({strict: true, allErrors: true, allowUnionTypes: true,
                         validateFormats: true});
addFormats(ajv);
ajv.addFormat('binary', true);  // OpenAPI's marker for raw bytes; not a string format to check
// The OpenAPI 3.1 base dialect's own keywords, which annotate and never constrain.
for (const keyword of ['example', 'discriminator', 'xml', 'externalDocs']) {
  ajv.addKeyword({keyword});
}
// The document is added whole so that its schemas' $refs (#/components/...) resolve; its own
// top-level members are no schema keywords, so they are declared as ones that check nothing.
for (const keyword of ['openapi', 'info', 'jsonSchemaDialect', 'servers', 'paths', 'webhooks',
                       'components', 'security', 'tags']) {
  ajv.addKeyword({keyword});
}
const CONTRACT_ID = 'https://vsm.invalid/openapi.json';
ajv.addSchema({...contract, $id: CONTRACT_ID}, CONTRACT_ID, undefined, false);

function pointer(parts) {
  return '#/' + parts.map((p) => String(p).replace(/~/g, '~0').replace(/\//g, '~1')).join('/');
}
function resolve(ref) {
  if (!ref.startsWith('#/')) throw new Error('only local $refs are supported: ' + ref);
  let node = contract;
  for (const raw of ref.slice(2).split('/')) {
    const part = raw.replace(/~1/g, '/').replace(/~0/g, '~');
    if (node === undefined || !(part in node)) throw new Error('unresolved $ref ' + ref);
    node = node[part];
  }
  return node;
}
// An object of the contract and the JSON pointer it is at, following a $ref if it is one.
function deref(node, at) {
  while (node && typeof node.$ref === 'string') {
    at = node.$ref;
    node = resolve(node.$ref);
  }
  return {node, at};
}
const compiled = new Map();
function validatorAt(at) {
  if (!compiled.has(at)) compiled.set(at, ajv.compile({$ref: CONTRACT_ID + at}));
  return compiled.get(at);
}
function schemaErrors(at, value) {
  const validate = validatorAt(at);
  if (validate(value)) return [];
  return validate.errors.map((e) => (e.instancePath || '(root)') + ' ' + e.message +
                                    (e.params && Object.keys(e.params).length
                                       ? ' ' + JSON.stringify(e.params) : ''));
}

// ---- matching --------------------------------------------------------------------------------

const templates = Object.keys(contract.paths).map((template) => {
  let literal = 0;
  const source = template.split(/(\{[^}]+\})/).map((part) => {
    if (/^\{[^}]+\}$/.test(part)) return '([^/]+)';
    literal += part.length;
    return part.replace(/[.*+?^${}()|[\]\\]/g, '\\$&');
  }).join('');
  return {template, regex: new RegExp('^' + source + '$'), literal};
});
function matchPath(p) {
  const found = templates.filter((t) => t.regex.test(p));
  found.sort((a, b) => b.literal - a.literal);
  return found.length ? found[0].template : null;
}
function responseFor(operation, status, at) {
  const code = String(status);
  for (const key of [code, code[0] + 'XX', 'default']) {
    if (operation.responses && key in operation.responses) {
      return deref(operation.responses[key], at + '/responses/' + pointer([key]).slice(2));
    }
  }
  return null;
}
function mediaType(value) {
  return (value || '').split(';').map((s) => s.trim().toLowerCase()).filter(Boolean).join(';');
}
function isJson(type) {
  const base = type.split(';')[0];
  return base === 'application/json' || base.endsWith('+json');
}
function coerce(value, schema) {
  const type = schema && schema.type;
  if ((type === 'integer' || type === 'number') && /^-?\d+(\.\d+)?([eE][-+]?\d+)?$/.test(value)) {
    return Number(value);
  }
  return value;
}

// ---- one exchange ----------------------------------------------------------------------------

function check(ex) {
  const problems = [];
  const template = matchPath(ex.path);
  if (template === null) return {problems: ['no path of the contract matches ' + ex.path]};
  const method = ex.method.toLowerCase();
  const item = contract.paths[template];
  const operation = item[method];
  if (!METHODS.includes(method) || !operation) {
    return {template, problems: [ex.method + ' is not an operation of ' + template]};
  }
  const opAt = pointer(['paths', template, method]);
  const response = responseFor(operation, ex.status, opAt);
  const key = {method: ex.method.toUpperCase(), template, status: String(ex.status)};
  if (response === null) {
    return {key, template, problems: ['status ' + ex.status + ' is not documented for ' +
                                      key.method + ' ' + template]};
  }
  const headers = ex.headers || {};
  let body = Buffer.from(ex.body_b64 || '', 'base64');
  if ((headers['content-encoding'] || '').toLowerCase() === 'gzip' && body.length) {
    body = zlib.gunzipSync(body);
  }
  // Headers.
  if (!('x-request-id' in headers)) {
    problems.push('no X-Request-Id header');
  } else {
    problems.push(...schemaErrors(pointer(['components', 'headers', 'X-Request-Id', 'schema']),
                                  headers['x-request-id']).map((e) => 'X-Request-Id: ' + e));
  }
  for (const [name, raw] of Object.entries(response.node.headers || {})) {
    const h = deref(raw, response.at + '/headers/' + pointer([name]).slice(2));
    const value = headers[name.toLowerCase()];
    if (value === undefined) {
      if (h.node.required) problems.push('required header ' + name + ' is missing');
      continue;
    }
    if (h.node.schema) {
      const s = deref(h.node.schema, h.at + '/schema');
      problems.push(...schemaErrors(s.at, coerce(value, s.node)).map((e) => name + ': ' + e));
    }
  }
  // Body.
  const content = response.node.content;
  if (!content) {
    if (body.length) {
      problems.push('a body of ' + body.length + ' bytes where the contract has none');
    }
    return {key, template, problems};
  }
  const got = mediaType(headers['content-type']);
  const types = Object.keys(content);
  const type = types.find((t) => mediaType(t) === got) ||
               types.find((t) => !t.includes(';') && mediaType(t) === got.split(';')[0]);
  if (!type) {
    problems.push('Content-Type ' + JSON.stringify(headers['content-type']) +
                  ' is none of ' + types.join(', '));
    return {key, template, problems};
  }
  const media = content[type];
  const schemaAt = response.at + '/content/' + pointer([type]).slice(2) + '/schema';
  if (isJson(type)) {
    let value;
    try {
      value = JSON.parse(body.toString('utf8'));
    } catch (e) {
      problems.push('the body is not JSON: ' + e.message);
      return {key, template, problems};
    }
    if (media.schema) problems.push(...schemaErrors(schemaAt, value));
  } else if (type === 'text/event-stream') {
    const defs = (media.schema && media.schema.$defs) || {};
    for (const event of ex.events || []) {
      if (!(event.event in defs)) {
        problems.push('event ' + JSON.stringify(event.event) + ' has no schema in $defs');
        continue;
      }
      problems.push(...schemaErrors(schemaAt + '/$defs/' + pointer([event.event]).slice(2),
                                    event.data).map((e) => 'event ' + event.event + ' #' +
                                                           event.id + ': ' + e));
    }
  } else if (ex.status < 300 && body.length === 0) {
    problems.push('an empty ' + type + ' body');
  } else if (type === 'image/png' && !body.subarray(0, 8).equals(
                 Buffer.from([0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a]))) {
    problems.push('image/png without the PNG signature');
  } else if (type === 'model/gltf-binary' && body.subarray(0, 4).toString('latin1') !== 'glTF') {
    problems.push('model/gltf-binary without the GLB magic');
  }
  return {key, template, problems};
}

// ---- run -------------------------------------------------------------------------------------

let failures = 0;

// The example files the contract names (externalValue, relative to it) against their media
// types' schemas: Redocly checks inline examples only.
let examplesChecked = 0;
function checkExamples(content, at) {
  for (const [type, media] of Object.entries(content || {})) {
    if (!isJson(mediaType(type)) || !media.schema) continue;
    const schemaAt = at + '/content/' + pointer([type]).slice(2) + '/schema';
    for (const [name, raw] of Object.entries(media.examples || {})) {
      const example = deref(raw, '').node;
      if (!example.externalValue) continue;
      const file = path.resolve(path.dirname(opts.contract), example.externalValue);
      let problems;
      try {
        problems = schemaErrors(schemaAt, JSON.parse(fs.readFileSync(file, 'utf8')));
      } catch (e) {
        problems = [e.message];
      }
      examplesChecked += 1;
      if (problems.length) {
        failures += 1;
        console.log('FAIL example ' + name + ' (' + example.externalValue + ') at ' + at);
        for (const p of problems) console.log('     ' + p);
      }
    }
  }
}
for (const [template, item] of Object.entries(contract.paths)) {
  for (const method of METHODS) {
    const operation = item[method];
    if (!operation) continue;
    const opAt = pointer(['paths', template, method]);
    if (operation.requestBody) {
      const body = deref(operation.requestBody, opAt + '/requestBody');
      checkExamples(body.node.content, body.at);
    }
    for (const [status, raw] of Object.entries(operation.responses || {})) {
      const response = deref(raw, opAt + '/responses/' + pointer([status]).slice(2));
      checkExamples(response.node.content, response.at);
    }
  }
}
const exercised = new Set();
const keyText = (k) => k.method + ' ' + k.template + ' ' + k.status;
for (const ex of exchanges) {
  let result;
  try {
    result = check(ex);
  } catch (e) {
    result = {problems: ['checker error: ' + e.stack]};
  }
  if (result.key) exercised.add(keyText(result.key));
  const label = ex.method + ' ' + ex.path + (ex.query ? '?' + ex.query : '') + ' -> ' +
                ex.status + (ex.step ? '  [' + ex.step + ']' : '');
  if (result.problems.length) {
    failures += 1;
    console.log('FAIL ' + label);
    for (const p of result.problems) console.log('     ' + p);
  }
}

// Coverage.
const documented = new Set();
for (const [template, item] of Object.entries(contract.paths)) {
  for (const method of METHODS) {
    if (!item[method]) continue;
    for (const status of Object.keys(item[method].responses || {})) {
      documented.add(method.toUpperCase() + ' ' + template + ' ' + status);
    }
  }
}
const excluded = new Map();
for (const line of fs.readFileSync(opts.exclusions, 'utf8').split('\n')) {
  const text = line.trim();
  if (!text || text.startsWith('#')) continue;
  const m = /^(\S+)\s+(\S+)\s+(\S+)\s+(.+)$/.exec(text);
  if (!m) {
    failures += 1;
    console.log('FAIL exclusion line without METHOD PATH STATUS REASON: ' + text);
    continue;
  }
  excluded.set(m[1] + ' ' + m[2] + ' ' + m[3], m[4]);
}
for (const [k] of excluded) {
  if (!documented.has(k)) {
    failures += 1;
    console.log('FAIL exclusion names nothing in the contract: ' + k);
  } else if (exercised.has(k)) {
    failures += 1;
    console.log('FAIL exclusion was exercised after all (remove it): ' + k);
  }
}
const missing = [...documented].filter((k) => !exercised.has(k) && !excluded.has(k)).sort();
for (const k of missing) {
  failures += 1;
  console.log('FAIL not exercised: ' + k);
}

// Negative controls: the checker must reject these.
const controls = [];
const anyExchange = exchanges.find((ex) => check(ex).problems.length === 0);
if (anyExchange) controls.push(['an undocumented status', {...anyExchange, status: 299}]);
const summary = exchanges.find((ex) => ex.method === 'GET' && ex.status === 200 &&
                                       matchPath(ex.path) === '/v1/models/{m}' &&
                                       check(ex).problems.length === 0);
if (summary) {
  const value = JSON.parse(Buffer.from(summary.body_b64, 'base64').toString('utf8'));
  delete value.version;
  value.depth = 'deep';
  controls.push(['a model summary without its version and with a string depth',
                 {...summary, body_b64: Buffer.from(JSON.stringify(value)).toString('base64')}]);
}
if (controls.length !== 2) {
  failures += 1;
  console.log('FAIL the negative controls found no valid exchange to break');
}
for (const [what, ex] of controls) {
  if (check(ex).problems.length === 0) {
    failures += 1;
    console.log('FAIL negative control: ' + what + ' passed the checks (the checker is broken)');
  }
}

const total = documented.size;
console.log('check_exchanges: ' + exchanges.length + ' exchanges, ' +
            [...exercised].filter((k) => documented.has(k)).length + ' of ' + total +
            ' documented (method, path, status) exercised, ' + excluded.size + ' excluded, ' +
            controls.length + ' negative controls rejected, ' + examplesChecked +
            ' example files checked; ' + failures + ' failures');
process.exit(failures ? 1 : 0);
