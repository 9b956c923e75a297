from django.contrib import admin
from django.contrib.auth import views as auth_views
from django.urls import path, register_converter

from . import report_views, views
from .api import api


class RowId:
    """A row's id in an address: 1 to 18 digits, so that every one fits the database's 64-bit keys (a longer one
    matches no page: 404, not a database error)."""

    regex = "[0-9]{1,18}"

    def to_python(self, value):
        return int(value)

    def to_url(self, value):
        return str(value)


register_converter(RowId, "id")

handler400 = "clinic.views.bad_request"  # the refusal's own words (a field named), on the site's error page

urlpatterns = [
    path("admin/", admin.site.urls),
    path("api/", api.urls),
    path("healthz", views.healthz, name="healthz"),
    path("accounts/login/", auth_views.LoginView.as_view(), name="login"),
    path("accounts/logout/", auth_views.LogoutView.as_view(), name="logout"),
    path("", views.patients, name="patients"),
    path("patients/new", views.new_patient, name="new_patient"),
    path("patients/<id:patient_id>/", views.patient, name="patient"),
    path("patients/<id:patient_id>/edit", views.edit_patient, name="edit_patient"),
    path("patients/<id:patient_id>/visits/new", views.new_visit, name="new_visit"),
    path("patients/<id:patient_id>/trend.png", views.patient_trend, name="patient_trend"),
    path("patients/<id:patient_id>/compare/", views.comparison, name="comparison"),
    path("visits/<id:visit_id>/", views.visit, name="visit"),
    path("visits/<id:visit_id>/edit", views.edit_visit, name="edit_visit"),
    path("visits/<id:pk>/report.pdf", report_views.visit_report, name="visit_report"),
    path("comparisons/<id:pk>/report.pdf", report_views.comparison_report, name="comparison_report"),
    path("visits/<id:visit_id>/landmarks", views.correct_landmarks, name="correct_landmarks"),
    path("visits/<id:visit_id>/landmarks/undo", views.undo_landmarks, name="undo_landmarks"),
    path("visits/<id:visit_id>/landmarks/pick", views.pick_landmark, name="pick_landmark"),
    path("rigs/<str:serial>/", views.rig, name="rig"),
    path("rigs/<str:serial>/keys", views.issue_rig_key, name="issue_rig_key"),
    path("rigs/<str:serial>/keys/<str:prefix>/revoke", views.revoke_rig_key, name="revoke_rig_key"),
    path("rigs/<str:serial>/stability.svg", views.rig_stability_chart, name="rig_stability_chart"),
    path("pictures/<str:kind>/<id:pk>/<str:name>.png", views.picture, name="picture"),
    path("pictures/<str:kind>/<id:pk>/<str:name>/", views.picture_page, name="picture_page"),
    path("jobs/<uuid:job_id>/rerun", views.rerun, name="rerun"),
    path("clinics/<id:clinic_id>/members/", views.members, name="members"),
    path("clinics/<id:clinic_id>/members/add", views.add_member, name="add_member"),
    path("clinics/<id:clinic_id>/members/<id:member_id>/role", views.change_member_role, name="change_member_role"),
    path("clinics/<id:clinic_id>/members/<id:member_id>/remove", views.remove_member, name="remove_member"),
]
