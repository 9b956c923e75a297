from django.db import connection
from django.http import JsonResponse


def healthz(request):
    """Liveness for load balancers: the app answers and reaches its database."""
    try:
        with connection.cursor() as cursor:
            cursor.execute("SELECT 1")
        database = True
    except Exception:  # any database failure means "not healthy", not a 500
        database = False
    return JsonResponse({"status": "ok" if database else "degraded", "database": database},
                        status=200 if database else 503)
