// Sign in: the API key is exchanged once for a short-lived HttpOnly session cookie and never kept.
import { h } from "../../dom.js";
import { api } from "../api-client.js";
import { showError } from "../messages.js";

// ctx: { page, route() } (router.js)
export function signInPage(ctx) {
  const key = h("input", {
    type: "password",
    name: "key",
    autocomplete: "off",
    placeholder: "pgs_...",
    "aria-label": "API key",
    size: 60,
  });
  const message = h("div", { class: "pgs-message" });
  const form = h(
    "form",
    {
      class: "pgs-card",
      id: "sign-in",
      onsubmit: async (e) => {
        e.preventDefault();
        const value = key.value.trim();
        key.value = ""; // the key is not kept anywhere once sent
        try {
          await api("POST", "/app/session", { key: value });
          ctx.route();
        } catch (err) {
          showError(message, err);
        }
      },
    },
    h("h2", {}, "Sign in"),
    h(
      "p",
      { class: "pgs-message" },
      "Paste an API key (panogs keys create --name you). It is exchanged for a session cookie and not stored.",
    ),
    key,
    " ",
    h("button", { type: "submit" }, "Sign in"),
    message,
  );
  ctx.page.replaceChildren(form);
  key.focus();
}
