// The one DOM helper of the app and the viewer: h("li", { class, onclick, "data-x": 1 }, ...children).
// attrs: "class" sets the class name, "style" an object of CSSOM properties (never a style attribute: the app's
// Content-Security-Policy, style-src 'self', refuses those), "on<event>" adds a listener, true is an empty
// attribute, and false, null and undefined leave the attribute out. Null and undefined children are skipped.
export function h(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (value === undefined || value === null || value === false) continue;
    if (key === "class") node.className = value;
    else if (key === "style") Object.assign(node.style, value);
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, value === true ? "" : value);
  }
  for (const child of children) if (child !== null && child !== undefined) node.append(child);
  return node;
}
