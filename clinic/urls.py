from django.contrib import admin
from django.contrib.auth import views as auth_views
from django.urls import path

from . import report_views, views
from .api import api

urlpatterns = [
    path("admin/", admin.site.urls),
    path("api/", api.urls),
    path("healthz", views.healthz, name="healthz"),
    path("accounts/login/", auth_views.LoginView.as_view(), name="login"),
    path("accounts/logout/", auth_views.LogoutView.as_view(), name="logout"),
    path("", views.patients, name="patients"),
    path("patients/new", views.new_patient, name="new_patient"),
    path("patients/<int:patient_id>/", views.patient, name="patient"),
    path("patients/<int:patient_id>/edit", views.edit_patient, name="edit_patient"),
    path("patients/<int:patient_id>/visits/new", views.new_visit, name="new_visit"),
    path("patients/<int:patient_id>/trend.png", views.patient_trend, name="patient_trend"),
    path("patients/<int:patient_id>/compare/", views.comparison, name="comparison"),
    path("visits/<int:visit_id>/", views.visit, name="visit"),
    path("visits/<int:visit_id>/edit", views.edit_visit, name="edit_visit"),
    path("visits/<int:pk>/report.pdf", report_views.visit_report, name="visit_report"),
    path("comparisons/<int:pk>/report.pdf", report_views.comparison_report, name="comparison_report"),
    path("visits/<int:visit_id>/landmarks", views.correct_landmarks, name="correct_landmarks"),
    path("visits/<int:visit_id>/landmarks/undo", views.undo_landmarks, name="undo_landmarks"),
    path("visits/<int:visit_id>/landmarks/pick", views.pick_landmark, name="pick_landmark"),
    path("rigs/<str:serial>/", views.rig, name="rig"),
    path("rigs/<str:serial>/keys", views.issue_rig_key, name="issue_rig_key"),
    path("rigs/<str:serial>/keys/<str:prefix>/revoke", views.revoke_rig_key, name="revoke_rig_key"),
    path("rigs/<str:serial>/stability.svg", views.rig_stability_chart, name="rig_stability_chart"),
    path("pictures/<str:kind>/<int:pk>/<str:name>.png", views.picture, name="picture"),
    path("pictures/<str:kind>/<int:pk>/<str:name>/", views.picture_page, name="picture_page"),
    path("jobs/<uuid:job_id>/rerun", views.rerun, name="rerun"),
    path("clinics/<int:clinic_id>/members/", views.members, name="members"),
    path("clinics/<int:clinic_id>/members/add", views.add_member, name="add_member"),
    path("clinics/<int:clinic_id>/members/<int:member_id>/role", views.change_member_role, name="change_member_role"),
    path("clinics/<int:clinic_id>/members/<int:member_id>/remove", views.remove_member, name="remove_member"),
]
