"""Reports on paper: one PDF of at most two A4 pages per visit and per comparison.

Drawn with matplotlib's PDF backend (already a dependency, nothing to install):
each page is an A4 figure on which :class:`Sheets` places lines of text,
tables and the stored pictures from top to bottom, and starts the second page
when the first is full. What a report says is what the pages say: the verdict,
the scan quality and the index rows come from the pages' own helpers in
:mod:`clinic.views`, the words from :mod:`clinic.labels`, the trend picture from
the same drawing the history page shows.

A download is not drawn again (about a second) while nothing it shows has changed: :func:`report_state` names the
state of everything a report can show, the laid out pages are drawn once per state and kept in Django's cache, and
the footer naming who produced the report, and when, is written on each download (:func:`stamp`).
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import logging
import re
import textwrap
from datetime import timezone as dt_timezone
from pathlib import Path

from django.core.cache import cache
from django.core.files.storage import default_storage
from django.utils import timezone
from django.utils.text import capfirst

from . import labels
# the pages' own helpers: the report calls them (rather than re-deriving a verdict) so that paper and screen never
# disagree
from .views import (best_of_visits, cached_mdc, comparison_index_rows, headline_of, index_rows_of,
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


class Picture:
    """A PNG placed on a sheet: its size in pixels (read from its header: no decoding while laying out), the key of
    what it shows (its bytes' digest unless given) and its bytes, decoded only when the sheets are drawn."""

    def __init__(self, png: bytes, key: str | None = None):
        self.png = png
        self.key = key or hashlib.sha256(png).hexdigest()
        self.width, self.height = png_size(png)


def png_size(data: bytes) -> tuple[int, int]:
    """(width, height) of a PNG, from its IHDR chunk."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    from matplotlib.image import imread

    a = imread(io.BytesIO(data), format="png")  # not a PNG's header: decoded, or refused, as drawing would
    return a.shape[1], a.shape[0]


class Sheets:
    """A4 pages filled top to bottom; at most ``max_pages``: what does not fit is left out, and said so.

    Laying out records each page's drawing operations (texts, rules, shades, pictures, in points from the page's
    top left corner) without matplotlib; :meth:`pdf` and :meth:`png` draw them. The ``footer`` (who produced the
    report, and when) is the one per-download line: it is not among the recorded operations, so that
    :meth:`fingerprint` names what the report shows and :meth:`static_pdf` draws it once for every download
    (:func:`stamp` writes the footer on)."""

    def __init__(self, running_head: str, footer: str, max_pages: int = MAX_PAGES):
        self.running_head, self.footer, self.max_pages = running_head, footer, max_pages
        self.w, self.h = A4_IN[0] * PT, A4_IN[1] * PT
        self.pages: list[list[tuple]] = []
        self.y, self.overflow, self.core = 0.0, False, True
        self._new_page()

    # -- pages --------------------------------------------------------------------------------------------------------
    def _new_page(self):
        self.pages.append([])
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

    # -- laying out ---------------------------------------------------------------------------------------------------
    def text_at(self, x, y, s, size, bold=False, color=INK, ha="left", va="top"):
        s = plain(s)
        self.core = self.core and core_font_fits(s)
        self.pages[-1].append(("text", x, y, s, size, bold, color, ha, va))

    def text_width(self, s: str, size: float, bold=False) -> float:
        return 1.05 * size * sum(_advance(c, bold) for c in s)  # 5 %: a hinted preview (PNG) draws wider

    def wrap(self, s: str, size: float, width: float, bold=False) -> list[str]:
        """Greedy word wrap to ``width`` points (a line's width is the sum of its characters' advances: each word
        adds its own and a space's)."""
        lines, scale, space = [], 1.05 * size, _advance(" ", bold)
        for paragraph in plain(str(s)).split("\n"):
            line, line_w = "", 0.0
            for word in paragraph.split(" "):
                word_w = sum(_advance(c, bold) for c in word)
                if line and scale * (line_w + space + word_w) > width:
                    lines.append(line)
                    line, line_w = word, word_w
                elif line:
                    line, line_w = f"{line} {word}", line_w + space + word_w
                else:
                    line, line_w = word, word_w
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
        self.pages[-1].append(("rule", MARGIN_X, MARGIN_X + self.width, self.y, color, lw))
        self.y += 4

    def _shade(self, x, y, w, h, color=SHADE):
        self.pages[-1].append(("shade", x, y, w, h, color))

    def images(self, pngs: list, max_h: float, min_h: float = 150.0, caption: str | None = None):
        """Pictures (PNG bytes or :class:`Picture`) side by side, as large as the width and the page's remaining
        room allow (down to ``min_h``)."""
        pictures = [p if isinstance(p, Picture) else Picture(p) for p in pngs if p]
        if not pictures:
            return
        gap = 8.0
        caption_h = 0.0 if not caption else 8 * 1.3 * len(self.wrap(caption, 8, self.width)) + 4
        ratios = [p.width / p.height for p in pictures]
        h = min(max_h, (self.width - gap * (len(pictures) - 1)) / sum(ratios))
        if self.room() - caption_h < min(h, min_h):
            if not self.ensure(min(h, min_h) + caption_h):
                return
        h = min(h, self.room() - caption_h)
        x = MARGIN_X + (self.width - (h * sum(ratios) + gap * (len(pictures) - 1))) / 2
        for p, r in zip(pictures, ratios):
            self.pages[-1].append(("image", x, self.y, h * r, h, p))
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
        """The last operations, once: the note that something was left out, and each page's number."""
        if getattr(self, "_finished", False):
            return
        self._finished = True
        if self.overflow:  # said on the paper itself, so a reader knows the screen has more
            self.pages[-1].append(("text", MARGIN_X, self.h - MARGIN_BOTTOM + 4, "Not everything fitted on two pages: "
                                   "the page on screen has the rest.", 7.5, False, WARN, "left", "top"))
        n = len(self.pages)
        for k, ops in enumerate(self.pages, 1):
            s = f"page {k} of {n}"
            self.core = self.core and core_font_fits(s)
            ops.append(("text", self.w - MARGIN_X, self.h - FOOTER_Y, s, 7, False, MUTED, "right", "bottom"))

    def fingerprint(self) -> str:
        """A digest of everything the pages show, the per-download footer apart (pictures by their keys), and of
        the code that draws them: two reports with the same fingerprint are the same drawing."""
        self._finish()
        ops = [[op[:-1] + (op[-1].key,) if op[0] == "image" else op for op in page] for page in self.pages]
        return hashlib.sha256(repr((_code_state(), self.core, ops)).encode()).hexdigest()

    def _figures(self, footer: str | None) -> tuple[list, bool]:
        """The pages drawn with matplotlib, ``footer`` on each unless None; and whether the viewer's Helvetica
        writes every text."""
        from matplotlib.figure import Figure
        from matplotlib.image import imread
        from matplotlib.lines import Line2D
        from matplotlib.patches import Rectangle

        self._finish()
        core = self.core and (footer is None or core_font_fits(footer))
        # Helvetica's regular weight is "medium": asked so, the font lookup does not warn
        regular = "medium" if core else "normal"
        w, h = self.w, self.h
        figures = []
        for ops in self.pages:
            fig = Figure(figsize=A4_IN)
            if footer is not None:
                ops = [*ops, ("text", MARGIN_X, h - FOOTER_Y, footer, 7, False, MUTED, "left", "bottom")]
            for op in ops:
                if op[0] == "text":
                    _, x, y, s, size, bold, color, ha, va = op
                    # parse_math=False: a "$" in a name or a note is text, not mathematics
                    fig.text(x / w, 1 - y / h, s, fontsize=size, fontweight="bold" if bold else regular, color=color,
                             ha=ha, va=va, parse_math=False)
                elif op[0] == "rule":
                    _, x0, x1, y, color, lw = op
                    fig.add_artist(Line2D([x0 / w, x1 / w], [1 - y / h, 1 - y / h], color=color, lw=lw))
                elif op[0] == "shade":
                    _, x, y, sw, sh, color = op
                    fig.add_artist(Rectangle((x / w, 1 - (y + sh) / h), sw / w, sh / h, color=color, lw=0, zorder=-1))
                else:
                    _, x, y, iw, ih, picture = op
                    ax = fig.add_axes((x / w, 1 - (y + ih) / h, iw / w, ih / h))
                    ax.imshow(imread(io.BytesIO(picture.png), format="png"), interpolation="antialiased")
                    ax.set_axis_off()
            figures.append(fig)
        return figures, core

    def pdf(self, metadata: dict | None = None) -> bytes:
        """The whole report, its footer drawn by matplotlib."""
        return self._pdf(self.footer, metadata)

    def static_pdf(self) -> bytes:
        """The report without its footer, for :func:`stamp` to write the footer and the document's information on."""
        return self._pdf(None, None)

    def _pdf(self, footer, metadata) -> bytes:
        from matplotlib.backends.backend_pdf import PdfPages

        import matplotlib

        figures, core = self._figures(footer)
        buf = io.BytesIO()
        with matplotlib.rc_context({"pdf.use14corefonts": core, "pdf.compression": 6}), \
                PdfPages(buf, metadata=metadata or {}) as pdf:
            for fig in figures:
                pdf.savefig(fig)
        return buf.getvalue()

    def png(self, dpi: int = 70) -> bytes:
        """The pages side by side as one PNG (to look at a report, and for the documentation's screenshots)."""
        from matplotlib.figure import Figure
        from matplotlib.image import imread

        shots = []
        for fig in self._figures(self.footer)[0]:
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


@functools.lru_cache(maxsize=1)
def _code_state() -> str:
    """The code a report rests on (this module, the words, the pages' helpers, the trend's drawing, the changes'
    verdicts) and matplotlib's version."""
    import matplotlib

    from analysis import indices, pictures, repeatability

    from . import views

    return views.files_digest((__file__, labels.__file__, views.__file__, pictures.__file__, indices.__file__,
                               repeatability.__file__), salt=matplotlib.__version__)


# --- the per-download footer, written on a report drawn once -------------------------------------------------------

FOOTER_Y = 22.0  # points: the footer's bottom, above the page's bottom edge
FOOTER_SIZE = 7.0
# matplotlib places a text's bottom ("va=bottom") at the descent of "lp" below its baseline: Helvetica's 'p'
# reaches 207/1000 of the size below it (its AFM metrics), so the stamped footer sits where matplotlib draws it
FOOTER_BASELINE = FOOTER_Y + 0.207 * FOOTER_SIZE


def _pdf_string(s: str) -> bytes:
    """A PDF text string: a literal if ASCII, else UTF-16 with its byte order mark."""
    if s.isascii():
        return b"(" + re.sub(rb"([\\()])", rb"\\\1", s.encode("ascii")).replace(b"\r", b"\\r").replace(
            b"\n", b"\\n") + b")"
    return b"<FEFF" + s.encode("utf-16-be").hex().upper().encode() + b">"


def _pdf_date(t) -> bytes:
    t = t.astimezone(dt_timezone.utc)
    return f"(D:{t:%Y%m%d%H%M%S}Z)".encode()


def stamp(pdf: bytes, footer: str, metadata: dict) -> bytes:
    """``pdf``, a report from :meth:`Sheets.static_pdf`, with ``footer`` written at the foot of every page (in the
    viewer's Helvetica, where matplotlib would draw it) and ``metadata`` (Title, Author, Creator, CreationDate) as
    its document information: the per-download part of a report, added in a millisecond to a report drawn once.

    The file is written again with every object as matplotlib wrote it but three: each page's contents become
    ``[save state, matplotlib's page, restore state and the footer]``, its font dictionary gains the footer's font,
    and the document information is replaced; then a new cross-reference table. ``footer`` must fit Windows-1252
    (:func:`core_font_fits`). Raises ValueError if ``pdf`` is not laid out as matplotlib writes one."""
    tail = re.search(rb"startxref\s+(\d+)\s+%%EOF\s*$", pdf[-64:])
    if not tail:
        raise ValueError("no startxref at the end")
    start = int(tail.group(1))
    m = re.match(rb"xref\s+0 (\d+)\s+", pdf[start:start + 64])
    if not m:
        raise ValueError("not one cross-reference section from object 0")
    size = int(m.group(1))
    entries = re.findall(rb"(\d{10}) (\d{5}) ([nf])", pdf[start + m.end():start + m.end() + 20 * size + 64])[:size]
    trailer = pdf[start + m.end() + 20 * size:]
    root, info = re.search(rb"/Root (\d+) 0 R", trailer), re.search(rb"/Info (\d+) 0 R", trailer)
    if len(entries) != size or not root:
        raise ValueError("cross-reference table or trailer not understood")
    offsets = {k: int(e[0]) for k, e in enumerate(entries) if e[2] == b"n"}
    order = sorted(offsets, key=offsets.get)
    objects = {k: pdf[offsets[k]:offsets[order[i + 1]] if i + 1 < len(order) else start] for i, k in enumerate(order)}
    q_obj, font_obj, footer_obj = size, size + 1, size + 2
    new_size = size + 3
    info_obj = int(info.group(1)) if info else size + 3
    new_size += 0 if info else 1
    pages = [k for k, body in objects.items() if re.match(rb"\d+ 0 obj\s*<< /Type /Page\b", body)]
    if not pages:
        raise ValueError("no page")
    font_dicts = set()
    for k in pages:
        body = objects[k]
        resources = re.search(rb"/Resources (\d+) 0 R", body)
        font = resources and re.search(rb"/Font (\d+) 0 R", objects.get(int(resources.group(1)), b""))
        if not font or int(font.group(1)) not in objects:
            raise ValueError(f"page {k}: font resources not understood")
        font_dicts.add(int(font.group(1)))
        body, n = re.subn(rb"/Contents (\d+) 0 R", lambda c: b"/Contents [ %d 0 R %s 0 R %d 0 R ]"
                          % (q_obj, c.group(1), footer_obj), body, count=1)
        if n != 1:
            raise ValueError(f"page {k}: contents not understood")
        objects[k] = body
    for k in font_dicts:
        body = objects[k]
        end = body.rfind(b">>")
        if end < 0:
            raise ValueError(f"font dictionary {k} not understood")
        objects[k] = body[:end] + b"/FStamp %d 0 R " % font_obj + body[end:]
    r, g, b = (int(MUTED[i:i + 2], 16) / 255 for i in (1, 3, 5))
    text = re.sub(rb"([\\()])", rb"\\\1", footer.encode("cp1252"))
    content = (b"Q\nq\n%.6f %.6f %.6f rg\nBT /FStamp %g Tf\n%.3f %.3f Td\n(%s) Tj ET\nQ\n"
               % (r, g, b, FOOTER_SIZE, MARGIN_X, FOOTER_BASELINE, text))
    fields = b"".join(b"/%s %s " % (key.encode(), _pdf_date(v) if key == "CreationDate" else _pdf_string(str(v)))
                      for key, v in metadata.items() if v is not None)
    producer = info and re.search(rb"/Producer \((?:\\.|[^\\)])*\)", objects.get(info_obj, b""))
    fields += producer.group(0) + b" " if producer else b""
    objects[q_obj] = b"%d 0 obj\n<< /Length 2 >>\nstream\nq\n\nendstream\nendobj\n" % q_obj
    objects[font_obj] = (b"%d 0 obj\n<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding "
                         b">>\nendobj\n" % font_obj)
    objects[footer_obj] = (b"%d 0 obj\n<< /Length %d >>\nstream\n%s\nendstream\nendobj\n"
                           % (footer_obj, len(content), content))
    objects[info_obj] = b"%d 0 obj\n<< %s>>\nendobj\n" % (info_obj, fields)
    out = [pdf[:min(offsets.values())]]
    at, where = len(out[0]), {}
    for k in order + [k for k in sorted(objects) if k not in offsets]:
        where[k] = at
        out.append(objects[k])
        at += len(objects[k])
    out.append(b"xref\n0 %d\n0000000000 65535 f \n" % new_size)
    out.extend(b"%010d 00000 n \n" % where[k] if k in where else b"0000000000 65535 f \n" for k in range(1, new_size))
    out.append(b"trailer\n<< /Size %d /Root %s 0 R /Info %d 0 R >>\nstartxref\n%d\n%%%%EOF\n"
               % (new_size, root.group(1), info_obj, at))
    return b"".join(out)


# --- what a report is made of ---------------------------------------------------------------------------------------

def stored(name: str | None) -> bytes | None:
    if not name or not default_storage.exists(name):
        return None
    with default_storage.open(name, "rb") as fh:
        return fh.read()


TREND_SIZE_IN = (8.6, 5.4)  # its panel titles need 8.6 in
# A report's drawings are kept in Django's cache under the state of what they show (a new state, a new key: a
# landmark corrected, a comparison run again, a note edited, a new repeat pair changing the MDC): never stale, and
# dropped a day after they were last drawn
REPORT_CACHE_SECONDS = 24 * 3600

log = logging.getLogger(__name__)


def trend_picture(patient, until=None, scans=None) -> Picture | None:
    """The history page's trend picture (the same drawing of the same scans and MDCs as views.patient_trend) of the
    visits up to ``until``, drawn at a page's width: the page's picture, shrunk onto paper, has lettering too small
    to read. A report of an earlier visit shows the trend as it stood then. ``scans``: the patient's
    :func:`scans_of`, if already read. Drawn once per state of its scans' indices and the clinic's MDC, then taken
    from the cache."""
    from analysis import pictures

    best = best_of_visits(scans_of(patient) if scans is None else scans)
    recs = sorted((r for r in best.values() if r.indices and (until is None or r.session.visit.date <= until)),
                  key=lambda r: (r.session.visit.date, r.session.visit_id))  # the visits' order
    if not recs:
        return None
    series = [(str(r.session.visit.date), r.indices) for r in recs]
    mdc = {k: v["mdc"] for k, v in cached_mdc(patient.clinic).items()}
    figures = [(k, labels.label(k) + (f" ({labels.unit(k)})" if labels.unit(k) else ""))
               for k, _ in pictures.TREND_FIGURES]
    # what the drawing reads of each scan (pictures.trend_picture plots the figures' values only): hashed instead of
    # the whole indices, a twentieth of their size
    drawn = [[label, [_figure_value(ind, k) for k, _ in figures]] for label, ind in series]
    state = json.dumps([drawn, mdc, figures, TREND_SIZE_IN, _code_state()], sort_keys=True, default=str)
    key = f"torsoscan:report-trend:{hashlib.sha256(state.encode()).hexdigest()}"
    png = cache.get(key)
    if png is None:
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            out = pictures.trend_picture(series, Path(tmp) / "trend.png", mdc=mdc, figures=figures,
                                         size_in=TREND_SIZE_IN)
            png = Path(out).read_bytes()
        cache.set(key, png, REPORT_CACHE_SECONDS)
    return Picture(png, key=key)


def _figure_value(indices: dict, key: str) -> float | None:
    """``analysis.repeatability.flatten(indices).get(key)`` without flattening all of ``indices``: the numeric leaf at
    the dotted path ``key``, or None."""
    import math

    v = indices
    for part in key.split("."):
        if not isinstance(v, dict):
            return None
        v = v.get(part)
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        return float(v)
    return None


def trend_png(patient, until=None) -> bytes | None:
    """:func:`trend_picture`'s PNG."""
    picture = trend_picture(patient, until)
    return picture.png if picture else None


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
        rest = ("the scanner's own repeatability (same-day re-scans of simulated patients, reconstructed on a "
                "simulated rig like this clinic's)" if h["scanner_mdc"] else "too few of this clinic's same-day re-scans")
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
            sheets.para(f"was {c['was']}, now {c['now']}"
                        + (f"; largest now: {c['where']}" if c.get("where") else "")
                        + (f". {capfirst(c['reason'])}." if c.get("reason") else ""), 8,
                        color=MUTED, indent=16, after=2)

    if h["beyond"]:
        sheets.para("▲ Changed beyond the scanner's noise", 9.5, bold=True, color=FLAG, after=1)
        items(h["beyond"], True)
    elif h["judged"]:
        sheets.para("✓ No index changed beyond the scanner's noise.", 9.5, bold=True, color=OK, after=2)
    if h["unjudged"]:
        sheets.para("Changes without a noise estimate yet" if noise["ready"]
                    else "Changes (sizes only, no noise verdict)", 9.5, bold=True, after=1)
        items(h["unjudged"], False)
    if h["no_verdict"]:
        sheets.para("No verdict: a landmark was placed two ways", 9.5, bold=True, after=1)
        items(h["no_verdict"], False)
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
    scans = scans_of(p)
    labelled = {r.pk: r for r in scans}  # scan labels ("… · scan 2 of 2 · reason")
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
    _conventions_and_trend(sheets, p, l_date, scans)
    return sheets


def visit_sheets(request, visit) -> Sheets:
    p = visit.patient
    clinic = p.clinic
    scans = scans_of(p)
    best = best_of_visits(scans)  # each visit's scan, as best_scan(visit): one query for the whole history
    rec = best.get(visit.pk)
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
    upto = [best.get(v.pk) for v in visits[:visits.index(visit) + 1]]
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
    _conventions_and_trend(sheets, p, visit.date, scans)
    return sheets


def _conventions_and_trend(sheets: Sheets, p, until, scans):
    sheets.para(SIDE_CONVENTION + " " + MDC_WORDS, 7.5, color=MUTED, after=4)
    trend = trend_picture(p, until, scans)
    if trend and sheets.room() < TREND_MIN_H + 45 and len(sheets.pages) >= sheets.max_pages:
        sheets.overflow = True  # no room for a readable trend: not a heading without its picture either
    elif trend:
        sheets.heading("Trend over the visits")
        sheets.images([trend], max_h=330, min_h=TREND_MIN_H,
                      caption="Every index over the patient's visits; the shaded band is the scanner's noise (MDC) "
                              "about the first visit, red triangles lie beyond it.")


def comparison_pdf(request, comp) -> bytes:
    p = comp.later.session.visit.patient
    return _report(request, ("comparison", comp.pk), p, lambda: comparison_sheets(request, comp),
                   f"Comparison report, {p.name} ({p.identifier})")


def visit_pdf(request, visit) -> bytes:
    p = visit.patient
    return _report(request, ("visit", visit.pk), p, lambda: visit_sheets(request, visit),
                   f"Visit report, {p.name} ({p.identifier}), {visit.date}")


# --- drawn once per state ------------------------------------------------------------------------------------------
#
# Drawing a report's pages with matplotlib costs about a second; reading and laying out what it shows, a tenth of
# that at 10 000 patients (every scan's indices read for the trend and the headlines). So a download asks first for
# the state of what a report can show: one query of a digest per row of the patient's records (visits, capture
# sessions, jobs, reconstructions, comparisons: every column, the clinicians' and the clinic's names with them),
# the clinic's MDC and noise state, today's date (the age), the code. A state seen before names the drawing made
# of it (the laid out pages' fingerprint), and that drawing is kept: the footer naming who produced the report and
# when is written on it (stamp). A new state (a landmark corrected, a comparison run again, a note edited, a
# repeat pair added, midnight) is laid out again; only if its pages differ from every drawing kept are they drawn
# again. The pictures on the pages are named in those rows: the analysis stores every new drawing under a name of
# its own (analysis_step). Nothing of the user is in a kept drawing, and the view has checked access before.

@functools.lru_cache(maxsize=None)
def _state_sql(kind: str) -> str:
    """One query: a row per row of the patient's records a ``kind`` ("visit" or "comparison") report can read,
    the table's name then the MD5 of each column (every concrete column, from the models: a column added later is
    in it too) and of the names shown with it; padded with empty columns so that the tables make one union. Its
    parameters: the patient's id five times, then the visit's or the comparison's id."""
    from django.contrib.auth import get_user_model
    from django.db import connection

    from .models import CaptureSession, Clinic, Comparison, Job, Patient, Reconstruction, Visit

    q = connection.ops.quote_name
    t = {m: q(m._meta.db_table) for m in (CaptureSession, Clinic, Comparison, Job, Patient, Reconstruction, Visit,
                                          get_user_model())}
    patient_visits = f'{t[Visit]} v ON v.{q("id")} = s.{q("visit_id")} AND v.{q("patient_id")} = %s'
    sessions = f'{t[CaptureSession]} s ON s.{q("id")}'
    if kind == "visit":  # the headlines' comparisons: those of this visit's scans with the earlier ones
        comparisons = (f'{t[Comparison]} c JOIN {t[Reconstruction]} r ON r.{q("id")} = c.{q("later_id")} '
                       f'JOIN {sessions} = r.{q("session_id")} AND s.{q("visit_id")} = %s')
    else:
        comparisons = f'{t[Comparison]} c WHERE c.{q("id")} = %s'
    user = get_user_model()
    tables = [
        ("patient", Patient, "p", [f'cl.{q("name")}'],
         f'{t[Patient]} p JOIN {t[Clinic]} cl ON cl.{q("id")} = p.{q("clinic_id")} WHERE p.{q("id")} = %s'),
        ("visit", Visit, "v", [f"u.{q(user._meta.get_field(n).column)}" for n in ("first_name", "last_name",
                                                                                    "username")],
         f'{t[Visit]} v LEFT JOIN {t[user]} u ON u.{q("id")} = v.{q("clinician_id")} WHERE v.{q("patient_id")} = %s'),
        ("session", CaptureSession, "s", [], f"{t[CaptureSession]} s JOIN {patient_visits}"),
        ("job", Job, "j", [], f'{t[Job]} j JOIN {sessions} = j.{q("session_id")} JOIN {patient_visits}'),
        ("reconstruction", Reconstruction, "r", [],
         f'{t[Reconstruction]} r JOIN {sessions} = r.{q("session_id")} JOIN {patient_visits}'),
        ("comparison", Comparison, "c", [], comparisons)]
    columns = {label: [f"{alias}.{q(f.column)}" for f in model._meta.concrete_fields] + extra
               for label, model, alias, extra, _ in tables}
    width = max(len(c) for c in columns.values())
    selects = []
    for label, _, _, _, source in tables:
        digests = [f"MD5(COALESCE(CAST({c} AS TEXT), '<null>'))" for c in columns[label]]
        digests += ["''"] * (width - len(digests))
        selects.append(f"SELECT '{label}', {', '.join(digests)} FROM {source}")
    return " UNION ALL ".join(selects)


def report_state(what: tuple, patient) -> str:
    """A digest of everything a report of ``what`` (``("visit", pk)`` or ``("comparison", pk)``) on ``patient``
    can show: see above."""
    from django.db import connection

    kind, pk = what
    with connection.cursor() as cursor:
        cursor.execute(_state_sql(kind), [patient.pk] * 5 + [pk])
        rows = sorted(cursor.fetchall())
    clinic = patient.clinic
    state = json.dumps([kind, pk, str(timezone.localdate()), _code_state(), rows, cached_mdc(clinic),
                        noise_state(clinic)], sort_keys=True, default=str)
    return hashlib.sha256(state.encode()).hexdigest()


def _report(request, what: tuple, patient, layout, title: str) -> bytes:
    """The report's PDF for this download: ``layout()`` (its :class:`Sheets`) laid out and drawn once per state of
    what it shows, the footer naming who produced it and when written on (:func:`stamp`). A footer the viewer's
    Helvetica cannot write (a name such as "Łucja") is drawn with the whole report, each time."""
    metadata = _metadata(request, title)
    footer = _footer(request, patient.clinic)
    if not core_font_fits(footer):
        return layout().pdf(metadata)
    state_key = f"torsoscan:report-state:{report_state(what, patient)}"
    fingerprint = cache.get(state_key)
    static = cache.get(f"torsoscan:report-pdf:{fingerprint}") if fingerprint else None
    if static is None:
        sheets = layout()
        fingerprint = sheets.fingerprint()
        pdf_key = f"torsoscan:report-pdf:{fingerprint}"
        static = cache.get(pdf_key)
        if static is None:
            static = sheets.static_pdf()
            cache.set(pdf_key, static, REPORT_CACHE_SECONDS)
        cache.set(state_key, fingerprint, REPORT_CACHE_SECONDS)
    try:
        return stamp(static, footer, metadata)
    except ValueError as e:  # not expected: matplotlib wrote the file; the whole report then, drawn as before
        log.warning("report: the footer could not be written on the kept drawing (%s): drawn in full", e)
        return layout().pdf(metadata)
