"""Reports on paper: one PDF of at most two A4 pages per visit and per comparison.

Drawn with matplotlib's PDF backend (already a dependency, nothing to install):
each page is an A4 figure on which :class:`Sheets` places lines of text,
tables and the stored pictures from top to bottom, and starts the second page
when the first is full. What a report says is what the pages say: the verdict,
the scan quality and the index rows come from the pages' own helpers in
:mod:`clinic.views`, the words from :mod:`clinic.labels`, the trend picture from
the same drawing the history page shows.
"""

from __future__ import annotations

import functools
import io
import re
import textwrap

from django.core.files.storage import default_storage
from django.utils import timezone

from . import labels
# the pages' own helpers: the report calls them (rather than re-deriving a verdict) so that paper and screen never
# disagree
from .views import (best_of_visits, best_scan, cached_mdc, comparison_index_rows, headline_of, index_rows_of,
                    noise_state, not_measurable_of, patient_context, scan_quality, scans_of, span_words, verdict_of)

MAX_PAGES = 2
TREND_MIN_H = 130.0  # points: the trend drawn smaller than this is not worth its room
A4_IN = (8.27, 11.69)
PT = 72.0  # points per inch: the layout works in points from the page's top left corner
MARGIN_X, MARGIN_TOP, MARGIN_BOTTOM = 42.0, 36.0, 46.0
INK, MUTED, FLAG, OK, WARN, RULE, SHADE = "#1d2733", "#4f5965", "#a8322a", "#1a6e45", "#7a4a00", "#c9cfd6", "#eef1f5"

SIDE_CONVENTION = ("Left and right are the patient's own, as seen from behind. Sideways values are given with their "
                   "side in words (\"towards the patient's right\"); a rotation names the side of the back that is "
                   "turned backwards.")
MDC_WORDS = ("Scanner noise (MDC): the minimal detectable change, the smallest change that same-day re-scans show "
             "is more than the scanner's own noise; a change within it may be noise.")


def _date(d) -> str:
    return f"{d.day} {d:%b %Y}" if d else "–"


# The PDF's fonts: the viewer's own Helvetica (not embedded: a small file, drawn ten times faster than an embedded
# font, whose text layout costs milliseconds a line) whenever every text fits its Windows-1252 characters; else
# DejaVu Sans embedded, so that a name such as "Łucja" is printed as written, never with a "?". The pages'
# symbols outside Windows-1252 become words or plain characters on paper.
def plain(s: str) -> str:
    s = re.sub("[\u25b2\u2713\u26a0]\ufe0f? *", "", s)  # ▲ ✓ ⚠: the words beside them say it
    return s.replace("\u2192", "to").replace("\u2264", "<=").replace("\u2265", ">=")


def core_font_fits(s: str) -> bool:
    try:
        s.encode("cp1252")
    except UnicodeEncodeError:
        return False
    return True


@functools.lru_cache(maxsize=4096)
def _advance(char: str, bold: bool) -> float:
    """Width of a character at 1 pt in DejaVu Sans (wider than Helvetica: wrapped lines fit in either font)."""
    from matplotlib.font_manager import FontProperties, findfont, get_font

    font = get_font(findfont(FontProperties(family="DejaVu Sans", weight="bold" if bold else "normal")))
    font.set_size(100, 72)
    return font.load_char(ord(char)).linearHoriAdvance / 65536 / 100


class Sheets:
    """A4 pages filled top to bottom; at most ``max_pages``: what does not fit is left out, and said so."""

    def __init__(self, running_head: str, footer: str, max_pages: int = MAX_PAGES):
        self.running_head, self.footer, self.max_pages = running_head, footer, max_pages
        self.w, self.h = A4_IN[0] * PT, A4_IN[1] * PT
        self.pages, self.y, self.overflow, self.core = [], 0.0, False, True
        self._new_page()

    # -- pages --------------------------------------------------------------------------------------------------------
    def _new_page(self):
        from matplotlib.figure import Figure

        fig = Figure(figsize=A4_IN)
        self.pages.append(fig)
        self.y = MARGIN_TOP
        if len(self.pages) > 1:  # every sheet names its patient: pages get separated
            self.text_at(MARGIN_X, self.y, self.running_head, 8, color=MUTED)
            self.y += 16

    @property
    def width(self) -> float:
        return self.w - 2 * MARGIN_X

    def room(self) -> float:
        return self.h - MARGIN_BOTTOM - self.y

    def ensure(self, height: float) -> bool:
        """Whether ``height`` fits here, on a new page if needed; False (and noted) once the pages are full."""
        if height <= self.room():
            return True
        if len(self.pages) < self.max_pages:
            self._new_page()
            return height <= self.room()
        self.overflow = True
        return False

    # -- drawing ------------------------------------------------------------------------------------------------------
    def _fig_xy(self, x, y):
        return x / self.w, 1 - y / self.h

    def text_at(self, x, y, s, size, bold=False, color=INK, ha="left"):
        s = plain(s)
        self.core = self.core and core_font_fits(s)
        # parse_math=False: a "$" in a name or a note is text, not mathematics
        self.pages[-1].text(*self._fig_xy(x, y), s, fontsize=size, fontweight="bold" if bold else "normal",
                            color=color, ha=ha, va="top", parse_math=False)

    def text_width(self, s: str, size: float, bold=False) -> float:
        return 1.05 * size * sum(_advance(c, bold) for c in s)  # 5 %: a hinted preview (PNG) draws wider

    def wrap(self, s: str, size: float, width: float, bold=False) -> list[str]:
        """Greedy word wrap to ``width`` points."""
        lines = []
        for paragraph in plain(str(s)).split("\n"):
            line = ""
            for word in paragraph.split(" "):
                trial = f"{line} {word}" if line else word
                if line and self.text_width(trial, size, bold) > width:
                    lines.append(line)
                    line = word
                else:
                    line = trial
            lines.append(line)
        return lines

    def para(self, s: str, size=9.0, bold=False, color=INK, indent=0.0, after=3.0, leading=1.3):
        """A paragraph, wrapped; its lines may run over to the next page."""
        for line in self.wrap(s, size, self.width - indent, bold):
            if not self.ensure(size * leading):
                return
            self.text_at(MARGIN_X + indent, self.y, line, size, bold, color)
            self.y += size * leading
        self.y += after

    def heading(self, s: str, size=11.5, color=INK):
        # a heading never ends a page: keep room for it and what follows (a table's header and first row)
        if self.room() < size * 1.4 + 70 and len(self.pages) < self.max_pages:
            self._new_page()
        self.y += 4
        self.para(s, size, bold=True, color=color, after=2)

    def gap(self, h: float):
        self.y = min(self.y + h, self.h - MARGIN_BOTTOM)

    def rule(self, color=RULE, lw=0.6):
        from matplotlib.lines import Line2D

        x0, y0 = self._fig_xy(MARGIN_X, self.y)
        x1, _ = self._fig_xy(MARGIN_X + self.width, self.y)
        self.pages[-1].add_artist(Line2D([x0, x1], [y0, y0], color=color, lw=lw))
        self.y += 4

    def _shade(self, x, y, w, h, color=SHADE):
        from matplotlib.patches import Rectangle

        fx, fy = self._fig_xy(x, y + h)
        self.pages[-1].add_artist(Rectangle((fx, fy), w / self.w, h / self.h, color=color, lw=0, zorder=-1))

    def images(self, pngs: list[bytes], max_h: float, min_h: float = 150.0, caption: str | None = None):
        """Pictures side by side, as large as the width and the page's remaining room allow (down to ``min_h``)."""
        from matplotlib.image import imread

        arrays = [imread(io.BytesIO(p), format="png") for p in pngs if p]
        if not arrays:
            return
        gap = 8.0
        caption_h = 0.0 if not caption else 8 * 1.3 * len(self.wrap(caption, 8, self.width)) + 4
        ratios = [a.shape[1] / a.shape[0] for a in arrays]  # width / height
        h = min(max_h, (self.width - gap * (len(arrays) - 1)) / sum(ratios))
        if self.room() - caption_h < min(h, min_h):
            if not self.ensure(min(h, min_h) + caption_h):
                return
        h = min(h, self.room() - caption_h)
        x = MARGIN_X + (self.width - (h * sum(ratios) + gap * (len(arrays) - 1))) / 2
        for a, r in zip(arrays, ratios):
            fx, fy = self._fig_xy(x, self.y + h)
            ax = self.pages[-1].add_axes((fx, fy, h * r / self.w, h / self.h))
            ax.imshow(a, interpolation="antialiased")
            ax.set_axis_off()
            x += h * r + gap
        self.y += h + 4
        if caption:
            self.para(caption, 8, color=MUTED, after=4)

    def table(self, columns: list[tuple[str, float, str]], rows: list[list], size=7.8, header_size=7.8):
        """``columns``: (title, share of the width, "left" or "right"); ``rows``: lists of cell texts, or
        ``(text, colour, bold)`` tuples. Rows are not split; the header is repeated on a new page."""
        pad, leading = 3.0, 1.25
        widths = [share * self.width for _, share, _ in columns]

        def cells(values, sz, bold_all=False):
            out = []
            for v, w in zip(values, widths):
                text, color, bold = (v if isinstance(v, tuple) else (v, INK, bold_all))
                out.append((self.wrap("" if text is None else str(text), sz, w - 2 * pad, bold), color, bold))
            return out, max(len(c[0]) for c in out) * sz * leading + 2 * pad

        def draw(prepared, height, sz, shade=None):
            if shade:
                self._shade(MARGIN_X, self.y, self.width, height, shade)
            x = MARGIN_X
            for (lines, color, bold), w, (_, _, align) in zip(prepared, widths, columns):
                for k, line in enumerate(lines):
                    tx = x + w - pad if align == "right" else x + pad
                    self.text_at(tx, self.y + pad + k * sz * leading, line, sz, bold, color, ha=align)
                x += w
            self.y += height

        head, head_h = cells([c[0] for c in columns], header_size, bold_all=True)
        page = None
        for values in rows:
            body, body_h = cells(values, size)
            if page != len(self.pages) or body_h > self.room():
                if not self.ensure(head_h + body_h):
                    return
                draw(head, head_h, header_size, SHADE)
                page = len(self.pages)
            draw(body, body_h, size)
            self.rule()
            self.y -= 3

    # -- output -------------------------------------------------------------------------------------------------------
    def _finish(self):
        if getattr(self, "_finished", False):
            return
        self._finished = True
        if self.overflow:  # said on the paper itself, so a reader knows the screen has more
            self.text_at(MARGIN_X, self.h - MARGIN_BOTTOM + 4, "Not everything fitted on two pages: the page on "
                       "screen has the rest.", 7.5, color=WARN)
        n = len(self.pages)
        for k, fig in enumerate(self.pages, 1):
            for x, s, ha in ((MARGIN_X, self.footer, "left"), (self.w - MARGIN_X, f"page {k} of {n}", "right")):
                self.core = self.core and core_font_fits(s)
                fig.text(x / self.w, 22 / self.h, s, fontsize=7, color=MUTED, ha=ha, va="bottom", parse_math=False)

    def pdf(self, metadata: dict | None = None) -> bytes:
        from matplotlib.backends.backend_pdf import PdfPages

        import matplotlib

        self._finish()
        if self.core:  # Helvetica's regular weight is "medium": asked so, the font lookup does not warn
            for fig in self.pages:
                for t in fig.texts:
                    if t.get_fontweight() == "normal":
                        t.set_fontweight("medium")
        buf = io.BytesIO()
        with matplotlib.rc_context({"pdf.use14corefonts": self.core, "pdf.compression": 6}), \
                PdfPages(buf, metadata=metadata or {}) as pdf:
            for fig in self.pages:
                pdf.savefig(fig)
        return buf.getvalue()

    def png(self, dpi: int = 70) -> bytes:
        """The pages side by side as one PNG (to look at a report, and for the documentation's screenshots)."""
        from matplotlib.figure import Figure
        from matplotlib.image import imread

        self._finish()
        shots = []
        for fig in self.pages:
            b = io.BytesIO()
            fig.savefig(b, format="png", dpi=dpi)
            shots.append(imread(io.BytesIO(b.getvalue()), format="png"))
        sheet = Figure(figsize=(A4_IN[0] * len(shots) + 0.2 * (len(shots) - 1), A4_IN[1]), dpi=dpi,
                       facecolor="#9aa3ad")
        for k, a in enumerate(shots):
            ax = sheet.add_axes(((k * (A4_IN[0] + 0.2)) / sheet.get_figwidth(), 0,
                                 A4_IN[0] / sheet.get_figwidth(), 1))
            ax.imshow(a)
            ax.set_axis_off()
        b = io.BytesIO()
        sheet.savefig(b, format="png", dpi=dpi)
        return b.getvalue()


# --- what a report is made of ---------------------------------------------------------------------------------------

def stored(name: str | None) -> bytes | None:
    if not name or not default_storage.exists(name):
        return None
    with default_storage.open(name, "rb") as fh:
        return fh.read()


def trend_png(patient, until=None) -> bytes | None:
    """The history page's trend picture (the same drawing of the same scans and MDCs as views.patient_trend) of the
    visits up to ``until``, drawn at a page's width: the page's picture, shrunk onto paper, has lettering too small
    to read. A report of an earlier visit shows the trend as it stood then."""
    import tempfile
    from pathlib import Path

    from analysis import pictures

    visits = patient.visits.filter(date__lte=until) if until else patient.visits.all()
    series = [(v.date, rec.indices) for v in visits if (rec := best_scan(v)) and rec.indices]
    if not series:
        return None
    mdc = {k: v["mdc"] for k, v in cached_mdc(patient.clinic).items()}
    figures = [(k, labels.label(k) + (f" ({labels.unit(k)})" if labels.unit(k) else ""))
               for k, _ in pictures.TREND_FIGURES]
    with tempfile.TemporaryDirectory() as tmp:
        png = pictures.trend_picture([(str(d), ind) for d, ind in series], Path(tmp) / "trend.png", mdc=mdc,
                                     figures=figures, size_in=(8.6, 5.4))  # its panel titles need 8.6 in
        return Path(png).read_bytes()


def produced_by(request) -> str:
    user = request.user
    name = user.get_full_name().strip() or user.get_username()
    now = timezone.localtime()
    return f"Produced by {name} on {_date(now)} at {now:%H:%M} {now.tzname() or ''}".rstrip()


def _header(sheets: Sheets, clinic, title: str, p, ctx: dict, subtitle: str):
    sheets.text_at(MARGIN_X, sheets.y, clinic.name, 10, bold=True, color="#1d3557")
    sheets.text_at(MARGIN_X + sheets.width, sheets.y, title, 10, color="#1d3557", ha="right")
    sheets.y += 15
    sheets.rule(color="#1d3557", lw=1.2)
    sheets.y += 2
    sheets.para(p.name, 15, bold=True, after=1)
    who = [f"ID {p.identifier}"]
    who.append(f"born {_date(p.date_of_birth)} (age {ctx['age_now']} today)" if p.date_of_birth and ctx["age_now"]
               else "date of birth not recorded")
    if p.sex:
        who.append(p.get_sex_display())
    sheets.para(" · ".join(who), 9.5, after=1)
    sheets.para(subtitle, 9.5, after=4)
    sheets.rule()


def _verdict(sheets: Sheets, h: dict):
    """One headline as the pages' _verdict.html shows it: beyond the noise, without a verdict, within, growth."""
    if h["repeat"]:
        title = f"{h['title']} ({_date(h['later_date'])}): repeatability, not a change"
    else:
        title = f"{h['title']} ({_date(h['earlier_date'])} → {_date(h['later_date'])}, {h['span']})"
    sheets.heading(title, 10.5)
    noise = h["noise"]
    if not noise["ready"] and h["judged"]:
        rest = ("the scanner's own repeatability (same-day re-scans made when it was tested)" if h["scanner_mdc"]
                else "too few of this clinic's same-day re-scans")
        sheets.para(f"The noise verdicts below rest on {rest}: the clinic has {noise['pairs']} of the "
                    f"{noise['needed']} re-scans needed for its own.", 8.5, color=WARN)
    elif not noise["ready"]:
        sheets.para(f"No noise verdict is possible yet: the clinic needs {noise['needed']} same-day re-scans to tell "
                    f"a real change from the scanner's noise, and has {noise['pairs']}. The changes are listed with "
                    "their sizes only.", 8.5, color=WARN)
    if h["repeat"]:
        sheets.para("Two scans of the same visit: any difference is the scanner's noise (and the patient's posture).",
                    8.5)
    if not h["sides_agree"]:
        sheets.para("⚠ The two scans disagree on the patient's left and right: only the indices that do not depend "
                    "on the side are compared.", 8.5, color=WARN)

    def items(rows, with_mdc):
        for c in rows:
            extra = f"  (▲ beyond the scanner's noise of {c['mdc']})" if with_mdc else ""
            sheets.para(f"{c['label']}: {c['change']}{extra}", 8.8, bold=True, indent=8, after=0,
                        color=FLAG if with_mdc else INK)
            was, _, now = c["from_to"].partition(" → ")
            sheets.para((f"was {was}, now {now}" if now else was)
                        + (f"; largest now: {c['where']}" if c.get("where") else ""), 8, color=MUTED,
                        indent=16, after=2)

    if h["beyond"]:
        sheets.para("▲ Changed beyond the scanner's noise", 9.5, bold=True, color=FLAG, after=1)
        items(h["beyond"], True)
    elif h["judged"]:
        sheets.para("✓ No index changed beyond the scanner's noise.", 9.5, bold=True, color=OK, after=2)
    if h["unjudged"]:
        sheets.para("Changes without a noise estimate yet" if noise["ready"]
                    else "Changes (sizes only, no noise verdict)", 9.5, bold=True, after=1)
        items(h["unjudged"], False)
    if h["within"]:
        sheets.para("Within the scanner's noise: " + "; ".join(
            f"{c['label']} ({c['change']}, noise {c['mdc']})" for c in h["within"]) + ".", 8.5, after=2)
    for nm in h["not_measurable"]:
        sheets.para(_not_measurable_words(nm), 8.5, color=WARN)
    if h["growth"]:
        sheets.para("Growth (reported apart, not a deformity): " + "; ".join(
            f"{c['label']} {c['change']} ({c['from_to']})" for c in h["growth"]) + ".", 8.5, after=2)


def _not_measurable_words(nm: dict) -> str:
    reason = nm["reason"].rstrip(".")
    return (f"Not measurable on {nm['when']}" + (f": {', '.join(nm['indices'])}" if nm["indices"] else "")
            + (f". {reason[:1].upper()}{reason[1:]}." if reason else "."))


def _quality_words(q: dict) -> str:
    return q["words"] + (": " + "; ".join(q["reasons"]) if q["reasons"] else "")


def _mdc_words(m) -> str:
    return "not known yet" if m is None else f"± {m:.2f}"


def _verdict_cell(growth, exceeds):
    if growth:
        return ("growth", MUTED, False)
    if exceeds:
        return ("▲ beyond noise", FLAG, True)
    if exceeds is False:
        return ("✓ within noise", OK, False)
    return ("no verdict yet", MUTED, False)


def _label(r) -> str:
    return r["label"] + (f" ({r['unit']})" if r["unit"] else "")


def _footer(request, clinic) -> str:
    return f"{produced_by(request)} · {clinic.name} · torsoscan surface scan report"


def _metadata(request, title: str) -> dict:
    return {"Title": title, "Author": request.user.get_username(), "Creator": "torsoscan",
            "CreationDate": timezone.now()}


# --- the two reports ------------------------------------------------------------------------------------------------

def comparison_sheets(request, comp) -> Sheets:
    earlier, later = comp.earlier, comp.later
    p = later.session.visit.patient
    clinic = p.clinic
    labelled = {r.pk: r for r in scans_of(p)}  # scan labels ("… · scan 2 of 2 · reason")
    e_label = getattr(labelled.get(earlier.pk), "scan_label", _date(earlier.session.visit.date))
    l_label = getattr(labelled.get(later.pk), "scan_label", _date(later.session.visit.date))
    e_date, l_date = earlier.session.visit.date, later.session.visit.date
    repeat = comp.is_repeat
    ctx = patient_context(p, l_date)
    mdc, noise = cached_mdc(clinic), noise_state(clinic)
    facing = comp.report.get("facing") or {}
    verdict = verdict_of(clinic, earlier, later, "Same-day re-scan" if repeat else "Between these scans", mdc, noise,
                         sides_agree=facing.get("consistent", True), growth=comp.report.get("growth"))
    title = (f"Same-day re-scan of {_date(l_date)}" if repeat
             else f"{_date(l_date)} against {_date(e_date)} ({span_words(e_date, l_date)})")
    sheets = Sheets(f"{p.name} · ID {p.identifier} · {title}", _footer(request, clinic))
    _header(sheets, clinic, "Surface scan report: comparison", p, ctx,
            f"{title}" + (f" · age {ctx['age_then']} at the later scan" if ctx["age_then"] else "")
            + f"\nEarlier scan: {e_label}. Later scan: {l_label}.")
    q_e, q_l = scan_quality(earlier), scan_quality(later)
    sheets.para(f"Scan quality: earlier {_quality_words(q_e).lower()}; later {_quality_words(q_l).lower()}.", 8.5)
    _verdict(sheets, verdict)

    sheets.heading("Deformation map")
    deformation = stored((comp.pictures or {}).get("deformation"))
    if deformation is None:
        sheets.para("The deformation map of these two scans has not been drawn.", 8.5, color=MUTED)
    sheets.images([deformation], max_h=330, min_h=200,
                  caption="How the surface moved from the earlier scan to the later one, in mm, on a fixed "
                          "scale of ±10 mm (red: outward, blue: inward), after lining the two up on the parts "
                          "that did not change. Light grey: within the scanner's noise; dark grey: arms, neck "
                          "and head, not compared.")

    sheets.heading("Indices")
    rows = comparison_index_rows(comp, mdc)
    sheets.table([("Index", 0.30, "left"), (_date(e_date), 0.18, "left"), (_date(l_date), 0.18, "left"),
                  ("Change", 0.10, "right"), ("Scanner noise (MDC)", 0.10, "right"), ("Verdict", 0.14, "left")],
                 [[(_label(r), INK, True), r["earlier"], r["later"], r["change"], _mdc_words(r["mdc"]),
                   _verdict_cell(r["growth"], r["exceeds_mdc"])] for r in rows], size=7.2)
    _conventions_and_trend(sheets, p, l_date)
    return sheets


def visit_sheets(request, visit) -> Sheets:
    p = visit.patient
    clinic = p.clinic
    rec = best_scan(visit)
    ctx = patient_context(p, visit.date)
    mdc, noise = cached_mdc(clinic), noise_state(clinic)
    sub = [f"Visit of {_date(visit.date)}"]
    if visit.reason:
        sub.append(visit.reason)
    if visit.clinician:
        sub.append(f"clinician {visit.clinician.get_full_name() or visit.clinician.get_username()}")
    if ctx["age_then"]:
        sub.append(f"age {ctx['age_then']} at the visit")
    sheets = Sheets(f"{p.name} · ID {p.identifier} · visit of {_date(visit.date)}", _footer(request, clinic))
    _header(sheets, clinic, "Surface scan report: visit", p, ctx, " · ".join(sub))
    if visit.notes:
        sheets.para(f"Notes: {textwrap.shorten(visit.notes, 400)}", 8.5)
    q = scan_quality(rec)
    sheets.heading(f"Scan quality: {q['words']}", 10.5, color={"good": OK, "repeat": FLAG}.get(q["verdict"], INK))
    for r in q["reasons"]:
        sheets.para(f"• {r[:1].upper()}{r[1:]}", 8.5, indent=8, after=1)
    if rec is None:
        sheets.para("No scan has been reconstructed for this visit.", 9)
        return sheets

    # the history page's headline, as it read with this visit the latest: since the baseline and the last visit
    visits = list(p.visits.order_by("date", "pk"))
    upto = [best_scan(v) for v in visits[:visits.index(visit) + 1]]
    headline = headline_of(p, upto, mdc, noise)
    for h in headline:
        _verdict(sheets, h)
    if not headline:
        sheets.para("No earlier scan to compare with: this is the patient's first.", 9)

    names = [n for n in ("torso-back", "asymmetry") if n in (rec.pictures or {})]
    if names:
        sheets.heading("Torso")
        sheets.images([stored(rec.pictures[n]) for n in names], max_h=220, min_h=150,
                      caption=" · ".join(labels.picture(n)[1] for n in names) + ".")

    sheets.heading("Surface indices")
    nm = not_measurable_of(rec, "this scan")
    if nm:
        sheets.para(_not_measurable_words(nm), 8.5, color=WARN)
    rows = []
    for key, r in zip(labels.TABLE_KEYS, index_rows_of(rec.indices)):
        if r["value"] is None and not r["not_measurable"]:
            continue  # not computed for this scan (an index newer than its analysis): no row of dashes on paper
        # the value with where it is largest on each side, in one cell (the page's two columns repeat the value)
        value = "; ".join(r["where"]) or r["value"] or "not measurable"
        rows.append([(_label(r) + (" · growth" if r["growth"] else ""), INK, True),
                     (value, WARN if r["not_measurable"] else INK, False),
                     "" if r["growth"] else _mdc_words((mdc.get(key) or {}).get("mdc"))])
    sheets.table([("Index", 0.30, "left"), ("Value, and where it is largest on each side", 0.59, "left"),
                  ("Scanner noise (MDC)", 0.11, "right")], rows, size=7.2)
    _conventions_and_trend(sheets, p, visit.date)
    return sheets


def _conventions_and_trend(sheets: Sheets, p, until):
    sheets.para(SIDE_CONVENTION + " " + MDC_WORDS, 7.5, color=MUTED, after=4)
    trend = trend_png(p, until)
    if trend and sheets.room() < TREND_MIN_H + 45 and len(sheets.pages) >= sheets.max_pages:
        sheets.overflow = True  # no room for a readable trend: not a heading without its picture either
    elif trend:
        sheets.heading("Trend over the visits")
        sheets.images([trend], max_h=330, min_h=TREND_MIN_H,
                      caption="Every index over the patient's visits; the shaded band is the scanner's noise (MDC) "
                              "about the first visit, red triangles lie beyond it.")


def comparison_pdf(request, comp) -> bytes:
    p = comp.later.session.visit.patient
    return comparison_sheets(request, comp).pdf(_metadata(request, f"Comparison report, {p.name} ({p.identifier})"))


def visit_pdf(request, visit) -> bytes:
    p = visit.patient
    return visit_sheets(request, visit).pdf(_metadata(request, f"Visit report, {p.name} ({p.identifier}), "
                                                               f"{visit.date}"))
