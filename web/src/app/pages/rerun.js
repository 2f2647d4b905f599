// The re-run form, shown in a job row's message box: the settings a person changes as fields (checked as typed), the
// fit on or off, the vocabulary, and the other settings as raw JSON under "advanced". A refusal (the form's own check
// or the server's) shows inside the form and keeps everything typed; a run closes the form with a confirmation.
import { h } from "../../dom.js";
import { api } from "../api-client.js";
import { showError } from "../messages.js";
import { shortId, vocabularyBody, vocabularyText } from "../rules.js";
import { FIELDS, buildSettings, checkField, splitSettings } from "../settings-form.js";

function fieldRow(field, text) {
  const input = h("input", {
    type: "text",
    name: field.key,
    "data-field": field.key,
    placeholder: `${field.placeholder} (default)`,
    "aria-label": field.label,
    title: field.help,
  });
  input.value = text;
  const note = h("span", { class: "pgs-field-note", "aria-live": "polite" });
  input.addEventListener("input", () => {
    const checked = checkField(field, input.value);
    input.setAttribute("aria-invalid", String(Boolean(checked.error)));
    note.textContent = checked.error || "";
  });
  return { input, row: h("label", { class: "pgs-field" }, h("span", {}, field.label), input, note) };
}

// job: the job re-run; message: the row's message box; refresh(): reload the table
export function rerunForm(job, message, refresh) {
  const start = splitSettings(job.config);
  const fields = FIELDS.map((field) => [field, fieldRow(field, start.texts[field.key])]);
  const fit = h("input", { type: "checkbox", name: "fit", "data-field": "fit" });
  fit.checked = start.fit;
  const vocabulary = h("input", {
    type: "text",
    name: "vocabulary",
    "aria-label": "vocabulary",
    placeholder: "scannet20 | matterport21 | lamp, rug, ... (empty: the job's)",
  });
  vocabulary.value = vocabularyText(job.vocabulary);
  const advanced = h("textarea", { rows: 4, name: "advanced", "aria-label": "other settings (JSON)" });
  advanced.value = Object.keys(start.rest).length ? JSON.stringify(start.rest, null, 1) : "";
  const problems = h("div", { class: "pgs-message", "data-role": "form-error", "aria-live": "polite" });
  const submit = h("button", { type: "submit" }, "Run");
  const onsubmit = async (e) => {
    e.preventDefault();
    const texts = Object.fromEntries(fields.map(([field, { input }]) => [field.key, input.value]));
    const built = buildSettings(texts, fit.checked, advanced.value);
    if (built.errors) return showError(problems, { message: "not run:", problems: built.errors });
    submit.disabled = true;
    try {
      const rerun = await api("POST", "/v1/jobs", {
        scene_id: job.scene_id,
        config: built.config,
        vocabulary: vocabularyBody(vocabulary.value, job.vocabulary),
        maps: job.maps || undefined, // a scene without its own maps needs the job's models again
      });
      message.className = "pgs-message pgs-good";
      message.replaceChildren(`re-run queued as job ${shortId(rerun.id)}`);
      refresh();
    } catch (err) {
      showError(problems, err);
    } finally {
      submit.disabled = false;
    }
  };
  const cancel = h("button", { type: "button", onclick: () => message.replaceChildren() }, "Close");
  const form = h(
    "form",
    { class: "pgs-rerun", onsubmit },
    ...fields.map(([, { row }]) => row),
    h("label", { class: "pgs-field" }, h("span", {}, "fit the Gaussian scene"), fit),
    h("label", { class: "pgs-field" }, h("span", {}, "vocabulary"), vocabulary),
    h(
      "details",
      {},
      h("summary", {}, "advanced: other settings as JSON (PipelineConfig overrides; the fields above win)"),
      advanced,
    ),
    problems,
    h("div", {}, submit, " ", cancel),
  );
  message.className = "pgs-message";
  message.replaceChildren(form);
}
