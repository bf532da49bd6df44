// Collects every script error, failed resource load, unhandled promise rejection and
// console.error of the page into window.__irtrackErrors. A classic script loaded first, so it
// sees the errors of the modules loaded after it; the browser test reads the list.
(function () {
  "use strict";
  var errors = [];
  window.__irtrackErrors = errors;
  function push(kind, text) {
    errors.push(kind + ": " + text);
  }
  // Capture phase also sees failed <script>/<link>/<img> loads, which do not bubble.
  window.addEventListener(
    "error",
    function (e) {
      if (e.target && e.target !== window && (e.target.src || e.target.href)) {
        push("resource", "failed to load " + (e.target.src || e.target.href));
      } else {
        push("error", (e.message || "unknown") + " at " + (e.filename || "?") + ":" + (e.lineno || 0));
      }
    },
    true
  );
  window.addEventListener("unhandledrejection", function (e) {
    var r = e.reason;
    push("unhandled rejection", r && r.stack ? r.stack : String(r));
  });
  var original = console.error;
  console.error = function () {
    push("console.error", Array.prototype.map.call(arguments, String).join(" "));
    return original.apply(console, arguments);
  };
})();
