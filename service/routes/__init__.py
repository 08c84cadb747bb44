"""The routes, one module per resource; `ROUTERS` is what the app includes."""

from . import health, jobs, models, page, scene, work

ROUTERS = (health.router, models.router, work.router, scene.router, jobs.router, page.router)
