// The re-run form's rules, no DOM: the settings a person changes as fields (read from the job's settings, checked as
// typed with the server's own ranges: panogs_core's ClusteringConfig, LabelingConfig, AppearanceConfig), the rest of
// the settings as raw JSON, and the request body built from both. A field left empty keeps the default; a field
// given wins over the same setting in the JSON.

// key: the dotted PipelineConfig path; parse(text) -> value or throws an Error that says what is expected.
export const FIELDS = [
  {
    key: "clustering.thresholds",
    label: "clustering thresholds",
    placeholder: "0.9, 0.8, 0.7, 0.6",
    help: "the affinity of each merge round: numbers in [-1, 1], each no larger than the one before",
    parse: parseThresholds,
    text: (value) => value.join(", "),
  },
  {
    key: "labeling.vote_min_fraction",
    label: "labelling vote purity",
    placeholder: "0.5",
    help: "a segment takes its majority class only when that class holds at least this share, in [0, 1]",
    parse: (text) => parseNumber(text, 0, 1),
    text: String,
  },
  {
    key: "labeling.min_instance_points",
    label: "smallest instance (primitives)",
    placeholder: "50",
    help: "instances with fewer primitives are dissolved: a whole number, 0 or more",
    parse: parseCount,
    text: String,
  },
];
export const FIT_KEY = "appearance.enabled";

function parseNumber(text, low, high) {
  const value = Number(text);
  if (text.trim() === "" || !Number.isFinite(value)) throw new Error(`"${text.trim()}" is not a number`);
  if (value < low || value > high) throw new Error(`${value} is outside [${low}, ${high}]`);
  return value;
}

function parseThresholds(text) {
  const values = text
    .split(/[,\s]+/)
    .filter(Boolean)
    .map((part) => parseNumber(part, -1, 1));
  if (!values.length) throw new Error("give one or more numbers");
  values.forEach((value, i) => {
    if (i && value > values[i - 1]) throw new Error(`${value} is larger than ${values[i - 1]} before it`);
  });
  return values;
}

function parseCount(text) {
  const value = parseNumber(text, 0, Number.MAX_SAFE_INTEGER);
  if (!Number.isInteger(value)) throw new Error(`${value} is not a whole number`);
  return value;
}

// A field's check as typed: { value } (undefined when empty: the default) or { error }.
export function checkField(field, text) {
  if (!text.trim()) return { value: undefined };
  try {
    return { value: field.parse(text) };
  } catch (err) {
    return { error: `${field.label}: ${err.message}` };
  }
}

function getPath(config, key) {
  return key.split(".").reduce((node, part) => (node && typeof node === "object" ? node[part] : undefined), config);
}

function setPath(config, key, value) {
  const parts = key.split(".");
  let node = config;
  for (const part of parts.slice(0, -1)) {
    if (!node[part] || typeof node[part] !== "object" || Array.isArray(node[part])) node[part] = {};
    node = node[part];
  }
  node[parts.at(-1)] = value;
}

// Without the key; a section left empty goes too.
function dropPath(config, key) {
  const [section, name] = key.split(".");
  if (!config[section] || typeof config[section] !== "object") return;
  delete config[section][name];
  if (!Object.keys(config[section]).length) delete config[section];
}

// The form's starting point from a job's settings: each field's text, the fit's box, and the other settings.
export function splitSettings(config) {
  const rest = structuredClone(config || {});
  const texts = {};
  for (const field of FIELDS) {
    const value = getPath(rest, field.key);
    texts[field.key] = value === undefined ? "" : field.text(value);
    dropPath(rest, field.key);
  }
  const fit = getPath(rest, FIT_KEY) !== false;
  dropPath(rest, FIT_KEY);
  return { texts, fit, rest };
}

// The settings to send: { config } or { errors: [...] } (every field's problem at once; nothing is sent).
// texts: key -> the field's text; fit: the box; restText: the advanced JSON ("" for none).
export function buildSettings(texts, fit, restText) {
  const errors = [];
  let config = {};
  if (restText.trim()) {
    try {
      config = JSON.parse(restText);
    } catch (err) {
      errors.push(`other settings: not valid JSON (${err.message})`);
    }
    if (!errors.length && (!config || typeof config !== "object" || Array.isArray(config))) {
      errors.push('other settings: expected a JSON object, such as {} or {"fusion": {...}}');
      config = {};
    }
  }
  for (const field of FIELDS) {
    const checked = checkField(field, texts[field.key] || "");
    if (checked.error) errors.push(checked.error);
    else if (checked.value !== undefined) setPath(config, field.key, checked.value);
  }
  if (fit)
    dropPath(config, FIT_KEY); // the box wins over the other settings, like every field
  else setPath(config, FIT_KEY, false);
  return errors.length ? { errors } : { config };
}
