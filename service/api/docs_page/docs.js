// The API docs page: Swagger UI (shipped by the swagger-ui-bundle package, served from this
// origin) on the service's own OpenAPI document. No inline script, so the page's
// Content-Security-Policy allows scripts from this origin only.
window.ui = SwaggerUIBundle({
  url: "/openapi.json",
  dom_id: "#swagger-ui",
  deepLinking: true,
  presets: [SwaggerUIBundle.presets.apis],
  layout: "BaseLayout",
  // Swagger UI's default sends the document's URL to validator.swagger.io for a badge: off, so
  // the page asks no third-party host anything (the CSP would block it anyway).
  validatorUrl: null,
});
