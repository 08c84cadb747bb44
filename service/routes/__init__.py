"""The routes, one module per resource; `ROUTERS` is what the app includes."""

from . import health, jobs, models, work

ROUTERS = (health.router, models.router, work.router, jobs.router)
