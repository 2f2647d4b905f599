// ESLint's recommended rules on the web code, plus a fence around the pure modules: they must run under
// `node --test`, so no DOM globals and no three.js or DOM-helper imports there.
import js from "@eslint/js";
import globals from "globals";

// Globals that browsers and Node 20 both have: what a pure module may use.
const SHARED = {
  atob: "readonly",
  console: "readonly",
  fetch: "readonly",
  TextDecoder: "readonly",
  TextEncoder: "readonly",
  URLSearchParams: "readonly",
};

const PURE = [
  "src/scene.js",
  "src/viewer/state.js",
  "src/viewer/url-state.js",
  "src/viewer/colours.js",
  "src/viewer/describe.js",
  "src/viewer/keys.js",
  "src/app/api-client.js",
  "src/app/rules.js",
  "src/app/routes.js",
];

export default [
  { ignores: ["node_modules/"] },
  js.configs.recommended,
  {
    rules: {
      eqeqeq: ["error", "always", { null: "ignore" }],
      "no-var": "error",
      "prefer-const": "error",
      "no-unused-vars": ["error", { caughtErrors: "none" }],
    },
  },
  { files: ["src/**/*.js"], ignores: PURE, languageOptions: { globals: globals.browser } },
  {
    files: PURE,
    languageOptions: { globals: SHARED },
    rules: {
      "no-restricted-imports": [
        "error",
        { patterns: [{ group: ["three", "three/*", "**/dom.js"], message: "a pure module: no three.js, no DOM" }] },
      ],
    },
  },
  { files: ["build.mjs", "eslint.config.js", "test/**/*.js"], languageOptions: { globals: globals.node } },
];
