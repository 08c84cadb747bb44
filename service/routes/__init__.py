"""The routes, one module per resource; `ROUTERS` is what the app includes."""

from . import captures, health, jobs, models, page, scene, work

ROUTERS = (health.router, models.router, work.router, scene.router, captures.router, jobs.router, page.router)
