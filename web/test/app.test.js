// The app's rules (routes, polling, job rows, the re-run form's vocabulary) and its API client's error handling.
import assert from "node:assert/strict";
import { afterEach, describe, it } from "node:test";
import { ApiError, api, currentSession, tusError } from "../src/app/api-client.js";
import { parseRoute, routePath, viewerHash } from "../src/app/routes.js";
import {
  POLL_IDLE_MS,
  POLL_LIVE_MS,
  cachedStages,
  cachedStagesText,
  fitRunning,
  fitText,
  jobMaps,
  jobProgressText,
  jobStateText,
  leftTheQueue,
  pollDelay,
  resultsReady,
  sceneFitted,
  startingJobText,
  tileReadouts,
  vocabularyBody,
  vocabularyText,
} from "../src/app/rules.js";

const JOB = "0b9a3c1e-2f4d-4e5a-8b6c-7d8e9f0a1b2c";

describe("routes", () => {
  it("opens the viewer on a job id with its view parameters", () => {
    const where = parseRoute(`#/jobs/${JOB}?mode=instance&sel=3`);
    assert.equal(where.page, "viewer");
    assert.equal(where.jobId, JOB);
    assert.equal(where.params.get("sel"), "3");
    assert.equal(viewerHash(JOB, where.params), `#/jobs/${JOB}?mode=instance&sel=3`);
  });

  it("sends anything else home", () => {
    for (const hash of ["", "#", "#/", "#/jobs/", "#/jobs/not-a-job-id", `#/jobs/${JOB}/more`, `#/scenes/${JOB}`]) {
      assert.deepEqual(parseRoute(hash), { page: "home" }, hash);
    }
  });

  it("treats a change of view parameters as the same page", () => {
    assert.equal(routePath(`#/jobs/${JOB}?mode=camera`), routePath(`#/jobs/${JOB}?mode=instance&cam=1,2,3,4,5,6`));
    assert.notEqual(routePath(`#/jobs/${JOB}`), routePath("#/"));
  });
});

describe("job rows and polling", () => {
  it("polls fast only while a job is live", () => {
    assert.equal(pollDelay([{ state: "succeeded" }, { state: "running" }]), POLL_LIVE_MS);
    assert.equal(pollDelay([{ state: "succeeded" }, { state: "failed" }, { state: "canceled" }]), POLL_IDLE_MS);
    assert.equal(pollDelay([]), POLL_IDLE_MS);
  });

  it("shows a cancel in flight and progress only while live", () => {
    assert.equal(jobStateText({ state: "running", cancel_requested: true }), "running (cancelling)");
    assert.equal(jobStateText({ state: "canceled", cancel_requested: true }), "canceled");
    assert.equal(jobProgressText({ state: "running", progress: 0.426 }), "43%");
    assert.equal(jobProgressText({ state: "succeeded", progress: 1 }), "");
  });
});

describe("a tiled job's tiles", () => {
  it("lists each tile and the merge with its progress while it runs, its state once not", () => {
    const job = {
      state: "running",
      tiles: [
        { index: 0, kind: "tile", state: "succeeded", stage: null, progress: 1, attempts: 1 },
        { index: 1, kind: "tile", state: "running", stage: "fusion", progress: 0.256, attempts: 2 },
        { index: 2, kind: "tile", state: "queued", stage: null, progress: 0, attempts: 2 },
        { index: 3, kind: "merge", state: "pending", stage: null, progress: 0, attempts: 0 },
      ],
    };
    assert.deepEqual(
      tileReadouts(job).map((t) => [t.label, t.text]),
      [
        ["tile 1", "succeeded"],
        ["tile 2", "26% fusion"],
        ["tile 3", "queued (attempt 2)"],
        ["merge", "pending"],
      ],
    );
    assert.deepEqual(tileReadouts({ state: "running", tiles: [] }), []); // ran whole
    assert.deepEqual(tileReadouts({ state: "running" }), []); // a server from before tiles
  });
});

describe("stages reused from an earlier job", () => {
  it("names the stages taken from the scene's checkpoints, in the status's order", () => {
    const rerun = { stage_cached: { validate: true, primitives: true, fusion: true, clustering: false } };
    assert.deepEqual(cachedStages(rerun), ["validate", "primitives", "fusion"]);
    assert.equal(cachedStagesText(rerun), "reused: validate, primitives, fusion");
    assert.equal(cachedStagesText({ stage_cached: { validate: false, clustering: false } }), "");
    assert.equal(cachedStagesText({}), ""); // a server from before the field
  });
});

describe("results before the Gaussian fit", () => {
  it("opens the viewer once the results are ready, the fit done or not", () => {
    assert.equal(resultsReady({ state: "running", results_ready: false }), false);
    assert.equal(resultsReady({ state: "running", results_ready: true }), true);
    assert.equal(resultsReady({ state: "canceled", results_ready: true }), true);
    assert.equal(resultsReady({ state: "succeeded" }), true); // a server from before the fit's own status
  });

  it("shows the fit's own progress while it runs, and how it ended", () => {
    const running = { state: "running", fit: { state: "running", progress: 0.256 } };
    assert.equal(fitRunning(running), true);
    assert.equal(fitText(running), "fitting 26%");
    assert.equal(fitText({ state: "running", fit: null }), "");
    assert.equal(fitText({ state: "succeeded", fit: { state: "succeeded", progress: 1 } }), "fitted");
    assert.equal(fitText({ state: "succeeded", fit: { state: "skipped", progress: 1 } }), "not fitted (off)");
    const failed = { state: "succeeded", fit: { state: "failed", progress: 0.5, error: "NumericalError: NaN" } };
    assert.equal(fitText(failed), "fit failed: NumericalError: NaN");
    assert.equal(fitRunning(failed), false);
    assert.equal(fitText({ state: "canceled", fit: { state: "canceled", progress: 0.5 } }), "fit canceled");
  });

  it("offers the photo view only once gaussians.ply is final", () => {
    assert.equal(sceneFitted({ state: "running", fit: { state: "running", progress: 0.3 } }), false);
    assert.equal(sceneFitted({ state: "succeeded", fit: { state: "succeeded", progress: 1 } }), true);
    assert.equal(sceneFitted({ state: "succeeded", fit: { state: "skipped", progress: 1 } }), true);
    assert.equal(sceneFitted({ state: "succeeded", fit: { state: "failed", progress: 0.4 } }), false);
    assert.equal(sceneFitted({ state: "canceled", fit: { state: "canceled", progress: 0.4 } }), false);
  });
});

describe("the re-run form's vocabulary", () => {
  const previous = {
    classes: [
      { name: "lamp", kind: "thing" },
      { name: "shelf", kind: "stuff" },
    ],
  };

  it("shows a built-in name or the class names", () => {
    assert.equal(vocabularyText("scannet20"), "scannet20");
    assert.equal(vocabularyText(previous), "lamp, shelf");
    assert.equal(vocabularyText(null), "");
  });

  it("sends a built-in name as is, a list as classes that keep their kinds", () => {
    assert.equal(vocabularyBody("  matterport21 ", previous), "matterport21");
    assert.equal(vocabularyBody("   ", previous), undefined);
    assert.deepEqual(vocabularyBody("shelf, rug,, lamp,", previous), {
      classes: [{ name: "shelf", kind: "stuff" }, { name: "rug" }, { name: "lamp", kind: "thing" }],
    });
    assert.deepEqual(vocabularyBody("lamp, rug", "scannet20"), { classes: [{ name: "lamp" }, { name: "rug" }] });
  });
});

describe("the upload form's job queued note", () => {
  it("gives way once the job's row shows it running or done", () => {
    const other = { id: "other", state: "running" };
    assert.equal(leftTheQueue([], JOB), false); // not listed yet
    assert.equal(leftTheQueue([other, { id: JOB, state: "queued" }], JOB), false);
    assert.equal(leftTheQueue([other, { id: JOB, state: "running" }], JOB), true);
    assert.equal(leftTheQueue([{ id: JOB, state: "succeeded" }], JOB), true); // a small job done within a poll
    assert.equal(leftTheQueue([other], JOB), false);
  });
});

describe("the upload form's 2D models", () => {
  const chosen = { masks: "slimsam", features: "clip-b16" };

  it("names a model only for each kind of map the scene's bundle lacks", () => {
    const bare = { name: "cab", has_mask_maps: false, has_feature_maps: false };
    assert.deepEqual(jobMaps(bare, chosen), chosen);
    assert.deepEqual(jobMaps({ ...bare, has_mask_maps: true }, chosen), { features: "clip-b16" });
    assert.equal(jobMaps({ has_mask_maps: true, has_feature_maps: true }, chosen), undefined);
    assert.equal(jobMaps({}, chosen), undefined); // a server from before the scene's two flags
    assert.equal(jobMaps(bare, { masks: "", features: "" }), undefined); // none offered: the server says what lacks
  });

  it("says which models will compute the maps", () => {
    assert.equal(startingJobText({ name: "cab" }, undefined), "scene cab is valid; starting a job ...");
    assert.equal(
      startingJobText({ name: "cab" }, chosen),
      "scene cab is valid; starting a job (its 2D maps computed by slimsam and clip-b16) ...",
    );
  });
});

describe("api client", () => {
  const realFetch = globalThis.fetch;
  afterEach(() => {
    globalThis.fetch = realFetch;
  });
  const answer = (status, body) => {
    const calls = [];
    globalThis.fetch = async (path, init) => {
      calls.push([path, init]);
      return new Response(body, { status });
    };
    return calls;
  };

  it("sends JSON with the app header and reads JSON back", async () => {
    const calls = answer(200, '{"id": "s1"}');
    assert.deepEqual(await api("POST", "/v1/scenes", { upload_id: "u1" }), { id: "s1" });
    const [path, init] = calls[0];
    assert.equal(path, "/v1/scenes");
    assert.deepEqual(init.headers, { "X-Panogs-App": "1", "Content-Type": "application/json" });
    assert.equal(init.body, '{"upload_id":"u1"}');
    assert.equal(init.credentials, "same-origin");
  });

  it("answers null for 204", async () => {
    answer(204, null);
    assert.equal(await api("DELETE", "/v1/jobs/1"), null);
  });

  it("raises the service's message and problems", async () => {
    answer(422, '{"message": "invalid bundle", "problems": ["a", "b"]}');
    await assert.rejects(api("POST", "/v1/scenes", {}), (err) => {
      assert.ok(err instanceof ApiError);
      assert.deepEqual([err.status, err.message, err.problems], [422, "invalid bundle", ["a", "b"]]);
      return true;
    });
    answer(502, "<html>bad gateway</html>");
    await assert.rejects(api("GET", "/v1/jobs"), { status: 502, message: "<html>bad gateway</html>" });
  });

  it("reads a 401 session as signed out, other failures as errors", async () => {
    answer(401, '{"message": "sign in"}');
    assert.equal(await currentSession(), null);
    answer(500, "{}");
    await assert.rejects(currentSession(), { status: 500, message: "HTTP 500" });
  });

  it("turns a refused tus upload into the service's problems", () => {
    const refused = {
      message: "tus: unexpected response",
      originalResponse: { getStatus: () => 413, getBody: () => '{"message": "too large", "problems": ["x"]}' },
    };
    assert.deepEqual(
      [tusError(refused).status, tusError(refused).message, tusError(refused).problems],
      [413, "too large", ["x"]],
    );
    const offline = tusError(new Error("network down"));
    assert.deepEqual([offline.status, offline.message, offline.problems], [0, "network down", []]);
  });
});
