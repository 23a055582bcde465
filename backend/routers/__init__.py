"""The back-end's HTTP routes, one module per part of the API, each an `APIRouter` named `router`.

`health` (/health, /v1/models), `detection` (/v1/detect), `missions` (rejection memory), `vehicles` (status,
decisions) and `supervisor` (the web page and its API). They get settings, stores and the caller from
`backend.dependencies`; `backend.app.create_app` builds the shared objects and includes every router.
"""
