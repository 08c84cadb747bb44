"""The routes, one module per resource; `ROUTERS` is what the app includes."""

from . import health, jobs, models, page, work

ROUTERS = (health.router, models.router, work.router, jobs.router, page.router)
