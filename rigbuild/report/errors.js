// Every error of the page (uncaught exceptions, console.error) is written into #rb-errors (data-count: how
// many), so that a headless browser's DOM dump shows them; runs first, before three.js and the viewer.
(function () {
  "use strict";
  var box = document.getElementById("rb-errors"), errors = [];
  function note(msg) {
    errors.push(String(msg));
    box.textContent = errors.join("\n");
    box.setAttribute("data-count", String(errors.length));
  }
  window.rbErrors = errors;
  window.rbNote = note;
  window.addEventListener("error", function (e) {
    note("error: " + e.message + " (" + (e.filename || "inline") + ":" + e.lineno + ")");
  });
  window.addEventListener("unhandledrejection", function (e) { note("unhandled rejection: " + e.reason); });
  var consoleError = console.error;
  console.error = function () {
    note("console.error: " + Array.prototype.join.call(arguments, " "));
    return consoleError.apply(console, arguments);
  };
})();
