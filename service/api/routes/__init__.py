"""One ``APIRouter`` per resource: registrations, tracking, artifacts, operations (health, metrics)."""
