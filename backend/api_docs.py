"""/docs served entirely by this process: Swagger UI's files come from the `swagger-ui-bundle-v2` package.

FastAPI's default /docs page loads Swagger UI from a CDN, which a field laptop at a rescue site cannot
reach. Here the page, its script, its style sheet and its start-up script are all local files, so /docs
works offline and under the service's Content-Security-Policy (no inline script).
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse, HTMLResponse, Response

ASSETS = {
    "swagger-ui-bundle.js": "text/javascript; charset=utf-8",
    "swagger-ui.css": "text/css; charset=utf-8",
    "favicon-32x32.png": "image/png",
}
_PAGE = """<!doctype html>
<html lang="en">
<head>
  <meta charset="utf-8">
  <title>{title} - API</title>
  <link rel="stylesheet" href="/docs/assets/swagger-ui.css">
  <link rel="icon" type="image/png" href="/docs/assets/favicon-32x32.png">
</head>
<body>
  <div id="swagger-ui"></div>
  <script src="/docs/assets/swagger-ui-bundle.js"></script>
  <script src="/docs/assets/start.js"></script>
</body>
</html>
"""
_START = """window.ui = SwaggerUIBundle({
  url: "/openapi.json",
  dom_id: "#swagger-ui",
  deepLinking: true,
  persistAuthorization: false,
  presets: [SwaggerUIBundle.presets.apis],
  layout: "BaseLayout",
});
"""


def swagger_ui_dir() -> Path:
    import swagger_ui_bundle  # swagger-ui-bundle-v2: Swagger UI 5, which reads FastAPI's OpenAPI 3.1

    return Path(swagger_ui_bundle.swagger_ui_path)


def add_offline_docs(app: FastAPI) -> None:
    """GET /docs and /docs/assets/{name}; create the app with docs_url=None and redoc_url=None."""
    folder = swagger_ui_dir()
    page = _PAGE.format(title=app.title)

    @app.get("/docs", include_in_schema=False)
    def docs() -> HTMLResponse:
        return HTMLResponse(page)

    @app.get("/docs/assets/{name}", include_in_schema=False)
    def asset(name: str) -> Response:
        if name == "start.js":
            return Response(_START, media_type="text/javascript; charset=utf-8")
        if name not in ASSETS:
            return Response(status_code=404)
        return FileResponse(
            folder / name, media_type=ASSETS[name], headers={"Cache-Control": "max-age=86400"}
        )
