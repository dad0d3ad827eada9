"""The HTTP API (FastAPI): jobs, datasets, health and metrics.

    from service.api import create_app
    app = create_app()

Modules: :mod:`.app` (factory, bind-address check), :mod:`.deps` (dependency aliases, auth),
:mod:`.models` (request/response models), :mod:`.errors` (error bodies and handlers),
:mod:`.prometheus` (metrics text), :mod:`.routers` (one per resource).
"""

from service.api.app import InsecureBindError, check_auth_config, create_app, is_loopback

__all__ = ["create_app", "check_auth_config", "is_loopback", "InsecureBindError"]
