from django.apps import AppConfig


class ClinicConfig(AppConfig):
    default_auto_field = "django.db.models.BigAutoField"
    name = "clinic"
    verbose_name = "torsoscan clinic"

    def ready(self):
        from . import audit  # noqa: F401  connects the audit trail's receivers (web, workers and commands alike)
