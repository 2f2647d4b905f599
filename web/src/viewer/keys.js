// The keyboard shortcuts: the table the help shows and the command each key runs. Pure, so the map is testable.

export const SHORTCUTS = [
  ["1 / 2 / 3", "colour by camera / semantic class / instance"],
  ["m", "next colour mode"],
  ["p", "photo: the fitted Gaussian scene, the colours of the mode over it (camera: only what is lit)"],
  ["f", "fit the scene in view"],
  ["[ / ]", "smaller / larger points"],
  ["/", "type a query"],
  ["Esc", "clear the selection and the query"],
  ["?", "show or hide this help"],
];

const COMMANDS = {
  1: "mode:camera",
  2: "mode:semantic",
  3: "mode:instance",
  m: "mode:next",
  p: "photo",
  f: "fit",
  "[": "smaller",
  "]": "larger",
  "/": "query",
  "?": "help",
  Escape: "escape",
};

// The command of a key event ({key, ctrlKey, metaKey, altKey}), or null: browser and system shortcuts
// (Ctrl/Cmd/Alt held) are left alone.
export function keyCommand(event) {
  if (event.ctrlKey || event.metaKey || event.altKey) return null;
  return Object.hasOwn(COMMANDS, event.key) ? COMMANDS[event.key] : null;
}
