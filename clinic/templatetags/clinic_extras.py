from django import template

register = template.Library()


@register.filter
def get(mapping, key):
    """``mapping[key]`` in a template, or None."""
    try:
        return mapping.get(key)
    except AttributeError:
        return None


@register.filter
def num(value, digits=1):
    """A number with ``digits`` decimals, or an en dash when there is none."""
    if value is None or value == "":
        return "–"
    try:
        return f"{float(value):.{int(digits)}f}"
    except (TypeError, ValueError):
        return str(value)


@register.filter
def signed(value, digits=1):
    if value is None:
        return "–"
    return f"{float(value):+.{int(digits)}f}"


@register.filter
def percent(value):
    if value is None or value == "":  # "": a field an older report does not have
        return "–"
    return f"{100 * float(value):.1f} %"


@register.filter
def xyz(values):
    """A point as "x y z" (mm, one decimal), or "" when it is unknown."""
    try:
        return " ".join(f"{float(v):.1f}" for v in values)
    except (TypeError, ValueError):
        return ""
