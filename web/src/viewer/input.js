// Pointer and keyboard input of the viewer. A press and release within a few pixels is a click (a pick); more is
// an orbit, which OrbitControls handles. Keys go through keys.js, and not while the user types in a field.
import { keyCommand } from "./keys.js";

const CLICK_SLOP_PX = 4;

// onClick(clientX, clientY); returns the function that unbinds
export function bindClicks(canvas, onClick) {
  let down = null;
  const press = (e) => (down = [e.clientX, e.clientY]);
  const release = (e) => {
    if (down && Math.hypot(e.clientX - down[0], e.clientY - down[1]) < CLICK_SLOP_PX) onClick(e.clientX, e.clientY);
    down = null;
  };
  canvas.addEventListener("pointerdown", press);
  canvas.addEventListener("pointerup", release);
  return () => {
    canvas.removeEventListener("pointerdown", press);
    canvas.removeEventListener("pointerup", release);
  };
}

// onCommand(name) for a shortcut while active() holds; Escape in a text field leaves the field. Returns the
// function that unbinds.
export function bindKeys(target, active, onCommand) {
  const onKey = (e) => {
    if (e.target instanceof HTMLInputElement || e.target instanceof HTMLTextAreaElement) {
      if (e.key === "Escape") e.target.blur();
      return;
    }
    if (!active()) return;
    const command = keyCommand(e);
    if (command) {
      e.preventDefault();
      onCommand(command);
    }
  };
  target.addEventListener("keydown", onKey);
  return () => target.removeEventListener("keydown", onKey);
}
