// ManiEval pages: a little progressive enhancement. Everything works without it except the
// live timeline, which falls back to reloading the page by hand.
"use strict";

// Forms that ask before doing something hard to undo.
document.addEventListener("submit", (event) => {
  const form = event.target;
  const question = form instanceof HTMLFormElement ? form.dataset.confirm : undefined;
  if (question && !window.confirm(question)) {
    event.preventDefault();
  }
});

// A page that answers a form's POST and shows something once (a new API token) takes the
// address of the page it belongs to: a reload then gets that page instead of resending the form.
const replaced = document.querySelector("[data-replace-url]");
if (replaced && window.history.replaceState) {
  window.history.replaceState(null, "", replaced.dataset.replaceUrl);
}

// "Copy" buttons for values shown once (new API tokens).
for (const button of document.querySelectorAll("button[data-copy]")) {
  button.addEventListener("click", () => {
    const source = document.getElementById(button.dataset.copy);
    const status = button.parentElement.querySelector(".copy-status");
    const say = (text) => { if (status) status.textContent = text; };
    if (!source || !navigator.clipboard) {
      say("Select the token and copy it by hand.");
      return;
    }
    navigator.clipboard.writeText(source.textContent.trim()).then(
      () => say("Copied."),
      () => say("Select the token and copy it by hand."),
    );
  });
}

// Tables wider than their box say so: a hint above them and a shadow on the edge that hides
// columns (the rank and participant columns are sticky, in the stylesheet).
for (const frame of document.querySelectorAll("[data-scroll-cue]")) {
  const scroller = frame.querySelector(".table-scroll");
  const hint = frame.querySelector(".scroll-hint");
  if (!scroller) continue;
  const update = () => {
    const hidden = scroller.scrollWidth - scroller.clientWidth;
    frame.classList.toggle("more-left", scroller.scrollLeft > 1);
    frame.classList.toggle("more-right", scroller.scrollLeft < hidden - 1);
    if (hint) hint.hidden = hidden <= 1;
  };
  scroller.addEventListener("scroll", update, { passive: true });
  if (window.ResizeObserver) new ResizeObserver(update).observe(scroller);
  update();
}

// The submission page follows its state through server-sent events until it ends, then
// swaps in the results without reloading the page.
function stateBadge(state) {
  const badge = document.createElement("span");
  badge.className = `state state-${state}`;
  badge.textContent = state.replace("_", " ");
  return badge;
}

function timelineEntry(t) {
  const item = document.createElement("li");
  item.append(stateBadge(t.to), " ");
  const time = document.createElement("time");
  time.dateTime = t.at;
  time.textContent = t.at_text;
  item.append(time, " ");
  if (t.attempt > 1) {
    const attempt = document.createElement("span");
    attempt.className = "muted";
    attempt.textContent = `attempt ${t.attempt}`;
    item.append(attempt, " ");
  }
  const reason = document.createElement("span");
  reason.className = "reason";
  reason.textContent = t.reason;
  item.append(reason);
  return item;
}

function followSubmission(live) {
  const state = document.getElementById("current-state");
  const reason = document.getElementById("current-reason");
  const timeline = document.getElementById("timeline");
  const progress = document.getElementById("progress");
  const bar = document.getElementById("progress-bar");
  const progressText = document.getElementById("progress-text");
  const status = document.getElementById("live-status");
  const events = new EventSource(live.dataset.events);
  status.hidden = false;

  events.addEventListener("transition", (message) => {
    const t = JSON.parse(message.data);
    timeline.append(timelineEntry(t));
    state.replaceChildren(stateBadge(t.to));
    reason.textContent = t.reason;
  });
  events.addEventListener("progress", (message) => {
    const p = JSON.parse(message.data);
    if (!p.total) return;
    progress.hidden = false;
    bar.max = p.total;
    bar.value = p.done || 0;
    progressText.textContent = `${p.done || 0} of ${p.total}` + (p.task ? ` (${p.task}, ${p.condition})` : "");
  });
  const finish = async () => {
    events.close();
    progress.hidden = true;
    status.textContent = "Finished.";
    live.dataset.final = "true";
    try {
      const response = await fetch(live.dataset.outcome, { credentials: "same-origin" });
      if (!response.ok) return;
      const page = new DOMParser().parseFromString(await response.text(), "text/html");
      const fresh = page.getElementById("outcome");
      const old = document.getElementById("outcome");
      if (fresh && old) old.replaceWith(document.adoptNode(fresh));
    } catch (error) {
      status.textContent = "Finished; reload the page to see the results.";
    }
  };
  events.addEventListener("end", (message) => {
    const end = JSON.parse(message.data);
    reason.textContent = end.reason;
    finish();
  });
  events.addEventListener("gone", () => {
    events.close();
    status.textContent = "This submission is no longer available.";
  });
}

const live = document.getElementById("live");
if (live && live.dataset.final === "false" && window.EventSource) {
  followSubmission(live);
}
