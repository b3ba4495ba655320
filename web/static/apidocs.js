// Starts Swagger UI on /docs (server/kit/apidocs.py): a file, not an inline script, so that
// the page keeps its Content-Security-Policy. Swagger's online validator is switched off:
// nothing leaves the server.
"use strict";

const root = document.getElementById("swagger-ui");
window.ui = SwaggerUIBundle({
  url: root.dataset.openapiUrl,
  dom_id: "#swagger-ui",
  layout: "BaseLayout",
  deepLinking: true,
  showExtensions: true,
  showCommonExtensions: true,
  validatorUrl: null,
  presets: [SwaggerUIBundle.presets.apis],
});
