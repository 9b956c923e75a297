"""The PDF reports' URLs: one per visit and one per comparison, scoped like their pages.

A report is a download of a patient's data, so each answer (a refusal too) is one ``download`` event in the
audit trail. The URLs name their record ``pk`` (not ``visit_id``), so the audit middleware, which records a
GET of a visit's URL as a view, leaves these to the view below: one event each, with the right action.
"""

import functools
import re

from django.contrib.auth.decorators import login_required
from django.db.models import F
from django.http import Http404, HttpResponse
from django.shortcuts import get_object_or_404

from . import audit, report
from .models import AuditEvent, Comparison, Visit, clinics_of


def _audited(object_type, model):
    def decorate(view):
        @functools.wraps(view)
        def wrapper(request, pk):
            status = 500
            try:
                response = view(request, pk)
                status = response.status_code
                return response
            except Http404:
                status = 404
                raise
            finally:
                patient_id, clinic_id = audit.patient_of_row(model, pk=pk)
                if patient_id is not None:  # a report of nobody's data does not exist: nothing was seen
                    audit.record(AuditEvent.DOWNLOAD, request=request, patient_id=patient_id, clinic_id=clinic_id,
                                 object_type=object_type, object_id=pk, status=status)
        return wrapper
    return decorate


def _pdf(data: bytes, name: str) -> HttpResponse:
    response = HttpResponse(data, content_type="application/pdf")
    safe = re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-") or "report"
    response["Content-Disposition"] = f'attachment; filename="{safe}.pdf"'
    response["Cache-Control"] = "no-store"  # a child's medical record: no browser or proxy keeps a copy
    return response


@login_required
@_audited("visit", Visit)
def visit_report(request, pk):
    v = get_object_or_404(Visit.objects.filter(patient__clinic__in=clinics_of(request.user))
                          .select_related("patient__clinic"), pk=pk)
    return _pdf(report.visit_pdf(request, v), f"torsoscan-{v.patient.identifier}-visit-{v.date}")


@login_required
@_audited("comparison", Comparison)
def comparison_report(request, pk):
    comp = get_object_or_404(Comparison.objects.filter(
        later__session__visit__patient__clinic__in=clinics_of(request.user),
        earlier__session__visit__patient=F("later__session__visit__patient"))
        .select_related("earlier__session__visit", "later__session__visit__patient__clinic"), pk=pk)
    later = comp.later.session.visit
    return _pdf(report.comparison_pdf(request, comp),
                f"torsoscan-{later.patient.identifier}-comparison-{comp.earlier.session.visit.date}-{later.date}")
