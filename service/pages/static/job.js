// A running job's page keeps its progress section current: every two seconds it fetches the
// section, rendered by the server (/jobs/ID/live), and puts it in place; it stops once the job
// has ended. Without script the page's <noscript> refresh reloads it instead.
(function () {
  "use strict";
  var section = document.getElementById("live");
  if (!section || section.dataset.live !== "true") { return; }
  var url = section.dataset.liveUrl;
  var ended = { succeeded: true, failed: true, cancelled: true };
  var failures = 0;

  function poll() {
    fetch(url, { credentials: "same-origin", headers: { "Accept": "text/html" }, cache: "no-store" })
      .then(function (response) {
        if (!response.ok) { throw new Error("HTTP " + response.status); }
        var state = response.headers.get("X-Job-State");
        return response.text().then(function (html) { return { html: html, state: state }; });
      })
      .then(function (result) {
        failures = 0;
        section.innerHTML = result.html;  // server-rendered and escaped, like the page itself
        section.dataset.state = result.state || "";
        if (ended[result.state]) {
          section.dataset.live = "false";
          return;
        }
        window.setTimeout(poll, 2000);
      })
      .catch(function () {
        failures += 1;  // the server restarting: back off, keep trying
        window.setTimeout(poll, Math.min(30000, 2000 * Math.pow(2, failures)));
      });
  }
  window.setTimeout(poll, 2000);
})();
