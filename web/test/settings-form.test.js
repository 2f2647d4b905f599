// The re-run form's rules: the fields read from a job's settings, checked as typed with the server's ranges, and
// the settings sent built from the fields, the fit's box and the advanced JSON.
import assert from "node:assert/strict";
import { describe, it } from "node:test";
import { FIELDS, buildSettings, checkField, splitSettings } from "../src/app/settings-form.js";

const field = (key) => FIELDS.find((f) => f.key === key);
const thresholds = field("clustering.thresholds");
const purity = field("labeling.vote_min_fraction");
const smallest = field("labeling.min_instance_points");

describe("checkField", () => {
  it("reads the thresholds as non-increasing numbers in [-1, 1]", () => {
    assert.deepEqual(checkField(thresholds, "0.9, 0.8 0.8,0.6"), { value: [0.9, 0.8, 0.8, 0.6] });
    assert.match(checkField(thresholds, "0.7, 0.9").error, /0\.9 is larger than 0\.7 before it/);
    assert.match(checkField(thresholds, "0.9, 1.5").error, /1\.5 is outside \[-1, 1\]/);
    assert.match(checkField(thresholds, "0.9, x").error, /"x" is not a number/);
  });

  it("keeps the default for an empty field and refuses what the server would", () => {
    assert.deepEqual(checkField(purity, "  "), { value: undefined });
    assert.deepEqual(checkField(purity, "0.25"), { value: 0.25 });
    assert.match(checkField(purity, "1.2").error, /^labelling vote purity: 1\.2 is outside \[0, 1\]/);
    assert.deepEqual(checkField(smallest, "80"), { value: 80 });
    assert.match(checkField(smallest, "80.5").error, /not a whole number/);
    assert.match(checkField(smallest, "-3").error, /outside/);
  });
});

describe("splitSettings and buildSettings", () => {
  const job = {
    clustering: { thresholds: [0.9, 0.7], two_hop_weight: 0.4 },
    labeling: { min_instance_points: 80 },
    appearance: { enabled: false, iterations: 2 },
  };

  it("puts a job's settings in the fields, the box and the rest", () => {
    const { texts, fit, rest } = splitSettings(job);
    assert.deepEqual(texts, {
      "clustering.thresholds": "0.9, 0.7",
      "labeling.vote_min_fraction": "",
      "labeling.min_instance_points": "80",
    });
    assert.equal(fit, false);
    assert.deepEqual(rest, { clustering: { two_hop_weight: 0.4 }, appearance: { iterations: 2 } });
    assert.deepEqual(job.labeling, { min_instance_points: 80 }, "the job's settings are left as they were");
    assert.deepEqual(splitSettings(undefined), { texts: { ...splitSettings({}).texts }, fit: true, rest: {} });
  });

  it("gives back the same settings when nothing is changed", () => {
    const { texts, fit, rest } = splitSettings(job);
    assert.deepEqual(buildSettings(texts, fit, JSON.stringify(rest)), { config: job });
  });

  it("lets the fields and the box win over the JSON, and lists every problem at once", () => {
    const texts = {
      "clustering.thresholds": "0.8",
      "labeling.vote_min_fraction": "",
      "labeling.min_instance_points": "",
    };
    const built = buildSettings(texts, true, '{"clustering": {"thresholds": [0.5]}, "appearance": {"enabled": false}}');
    assert.deepEqual(built, { config: { clustering: { thresholds: [0.8] } } });
    const bad = buildSettings({ ...texts, "labeling.min_instance_points": "x" }, true, "{nope");
    assert.equal(bad.errors.length, 2);
    assert.match(bad.errors[0], /other settings: not valid JSON/);
    assert.match(buildSettings(texts, true, "[1]").errors[0], /expected a JSON object/);
    assert.deepEqual(buildSettings({}, true, ""), { config: {} });
  });
});
