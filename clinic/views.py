from django.contrib.auth.decorators import login_required
from django.db import connection
from django.db.models import Q
from django.http import JsonResponse
from django.shortcuts import render

from .models import Patient, clinics_of


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


@login_required
def patients(request):
    """The patients of the user's clinics, with a search by name or identifier."""
    q = request.GET.get("q", "").strip()
    rows = Patient.objects.filter(clinic__in=clinics_of(request.user)).select_related("clinic")
    if q:
        rows = rows.filter(Q(name__icontains=q) | Q(identifier__icontains=q))
    return render(request, "clinic/patients.html", {"patients": rows, "q": q})
