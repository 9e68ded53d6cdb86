"""Verdicts on a paper's claims: what the suite found, and how it came to say so.

A method's report checks the claims of its paper. Each check gives a :class:`Claim` with one of five kinds:

``reproduces`` (:data:`REPRODUCES`)
    The suite measured the value and it lies within a stated tolerance of the paper's (:func:`judge`), or on the
    stated side of a bound (:func:`at_least`).
``does not reproduce`` (:data:`DOES_NOT_REPRODUCE`)
    The suite measured the value and it lies outside the tolerance; the verdict says by how much (:func:`judge`).
``consistent by calibration`` (:data:`BY_CALIBRATION`)
    The suite agrees because one of its inputs was calibrated to the paper (a network profile fitted to the
    paper's transfer time, a modelled bandwidth taken from the paper's figure): agreement is not evidence
    (:func:`by_calibration`).
``holds by construction`` (:data:`BY_CONSTRUCTION`)
    The claim follows from how the suite is built (a 32-bit bitmap is W·H·4 bytes) (:func:`by_construction`).
``not measurable here`` (:data:`NOT_MEASURABLE`)
    The suite cannot measure it; the verdict says why (:func:`not_measurable`).

Only the first two are measurements. A claim is serialisable (:meth:`Claim.as_dict`, :meth:`Claim.from_dict`,
:meth:`Claim.as_row`, :func:`claims_table`) so that the claims of every method can be gathered into one
paper-against-suite table. A report declares its claims in a :class:`ClaimList`, so that a claim whose runs are
not in the results keeps its row (``not measurable here``, saying what it needs).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

REPRODUCES = "reproduces"
DOES_NOT_REPRODUCE = "does not reproduce"
BY_CALIBRATION = "consistent by calibration"
BY_CONSTRUCTION = "holds by construction"
NOT_MEASURABLE = "not measurable here"
KINDS = (REPRODUCES, DOES_NOT_REPRODUCE, BY_CALIBRATION, BY_CONSTRUCTION, NOT_MEASURABLE)
#: The kinds that compare a measured value with the paper's under a tolerance.
MEASURED = (REPRODUCES, DOES_NOT_REPRODUCE)

#: Columns of :meth:`Claim.as_row`, in table order.
ROW_COLUMNS = ("id", "method", "statement", "source", "paper", "suite", "suite source", "setting", "tolerance",
               "verdict", "how")
#: The setting keys, in the order they are written.
SETTING_ORDER = ("scene", "backend", "resolution", "net", "protocol", "variant")


def format_value(value, unit: str = "") -> str:
    """``value`` with its unit: counts with thousands separators, other numbers to 4 significant digits."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    v = float(value)
    text = f"{v:,.0f}" if (v.is_integer() and abs(v) >= 1000) else f"{v:.4g}"
    return f"{text} {unit}".rstrip() if unit else text


@dataclass(frozen=True)
class Tolerance:
    """How far a measured value may lie from the paper's and still reproduce it: ``absolute`` (in the claim's
    unit) or ``relative`` (a fraction of the paper's value), exactly one. ``why`` says where the width comes
    from (the paper's rounding, its own spread, the noise of the suite's measurement)."""

    absolute: float | None = None
    relative: float | None = None
    why: str = ""

    def __post_init__(self):
        given = [v for v in (self.absolute, self.relative) if v is not None]
        if len(given) != 1:
            raise ValueError("a tolerance is either absolute or relative (exactly one)")
        if not math.isfinite(given[0]) or given[0] < 0:
            raise ValueError(f"a tolerance must be finite and >= 0, got {given[0]}")

    def allowed(self, paper_value: float) -> float:
        """The largest difference from ``paper_value`` that still reproduces it (in the claim's unit)."""
        return self.absolute if self.absolute is not None else self.relative * abs(paper_value)

    def describe(self, unit: str = "") -> str:
        """"±2 percentage points (absolute)", "±10 % of the paper's value (relative)"."""
        if self.absolute is not None:
            width = (f"±{self.absolute:g} percentage points" if unit == "%"
                     else f"±{format_value(self.absolute, unit)}")
            return f"{width} (absolute)"
        return f"±{100 * self.relative:g} % of the paper's value (relative)"

    def as_dict(self) -> dict:
        return {"absolute": self.absolute, "relative": self.relative, "why": self.why}


@dataclass(frozen=True)
class Claim:
    """One claim of a paper and the suite's verdict on it.

    ``id``: stable and unique across methods (``"000.network_share"``); ``statement``: the claim in words;
    ``source``: where the paper makes it (``"§5.2, Fig. 10"``); ``paper_value`` and ``unit``: the paper's number
    (None where the claim has none); ``suite_value``: the suite's number where it has one, and ``suite_source``
    where it comes from (``"run"``, ``"bench"``, ``"config"``); ``setting``: what the suite's number is for
    (scene, backend, resolution, net, protocol, variant, ...); ``tolerance``: for measured kinds; ``kind``: one of
    :data:`KINDS`; ``explanation``: how the verdict was reached.
    """

    id: str
    statement: str
    source: str
    kind: str
    explanation: str
    paper_value: float | None = None
    unit: str = ""
    suite_value: float | None = None
    suite_source: str = ""
    setting: dict = field(default_factory=dict)
    tolerance: Tolerance | None = None
    method: str = ""

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"unknown verdict kind '{self.kind}' (choose from {', '.join(KINDS)})")
        if not self.explanation.strip():
            raise ValueError(f"claim '{self.id}': a verdict must say how it was reached")
        if self.kind in MEASURED:
            if self.tolerance is None or not _finite(self.paper_value) or not _finite(self.suite_value):
                raise ValueError(f"claim '{self.id}': '{self.kind}' needs a paper value, a measured value and a "
                                 "tolerance (use judge())")

    @property
    def difference(self) -> float | None:
        """suite − paper, where both are numbers."""
        if _finite(self.paper_value) and _finite(self.suite_value):
            return float(self.suite_value) - float(self.paper_value)
        return None

    @property
    def verdict(self) -> str:
        """The kind and how it was reached, as one line."""
        return f"{self.kind}: {self.explanation}"

    def setting_text(self) -> str:
        keys = [k for k in SETTING_ORDER if k in self.setting] + sorted(set(self.setting) - set(SETTING_ORDER))
        return ", ".join(f"{k} {self.setting[k]}" for k in keys)

    def as_dict(self) -> dict:
        """JSON-able; :meth:`from_dict` reads it back."""
        return {"id": self.id, "method": self.method, "statement": self.statement, "source": self.source,
                "paper_value": _number(self.paper_value), "unit": self.unit, "suite_value": _number(self.suite_value),
                "suite_source": self.suite_source, "setting": dict(self.setting),
                "tolerance": self.tolerance.as_dict() if self.tolerance else None, "kind": self.kind,
                "explanation": self.explanation}

    @classmethod
    def from_dict(cls, d: dict) -> Claim:
        tol = d.get("tolerance")
        return cls(id=d["id"], method=d.get("method", ""), statement=d["statement"], source=d["source"],
                   paper_value=d.get("paper_value"), unit=d.get("unit", ""), suite_value=d.get("suite_value"),
                   suite_source=d.get("suite_source", ""), setting=dict(d.get("setting") or {}),
                   tolerance=Tolerance(**tol) if tol else None, kind=d["kind"], explanation=d["explanation"])

    def as_row(self) -> dict:
        """One flat row of the paper-against-suite table (:data:`ROW_COLUMNS`): values as text with units."""
        tol = ""
        if self.tolerance is not None:
            tol = self.tolerance.describe(self.unit) + (f": {self.tolerance.why}" if self.tolerance.why else "")
        return {"id": self.id, "method": self.method, "statement": self.statement, "source": self.source,
                "paper": format_value(self.paper_value, self.unit), "suite": format_value(self.suite_value, self.unit),
                "suite source": self.suite_source, "setting": self.setting_text(), "tolerance": tol,
                "verdict": self.kind, "how": self.explanation}


def _finite(value) -> bool:
    try:
        return value is not None and math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


def _number(value):
    return float(value) if _finite(value) else None


def _clause(text: str) -> str:
    """A clause to end with our own full stop."""
    return text.strip().rstrip(".")


def _sentence(*parts: str) -> str:
    return " ".join(p.strip() for p in parts if p and p.strip())


def judge(id: str, statement: str, source: str, paper_value: float, suite_value: float, unit: str,
          tolerance: Tolerance, *, setting: dict | None = None, suite_source: str = "run", method: str = "",
          note: str = "") -> Claim:
    """Compares a measured ``suite_value`` with ``paper_value`` under ``tolerance``: :data:`REPRODUCES` when
    ``|suite − paper| <= tolerance``, else :data:`DOES_NOT_REPRODUCE` with the excess. ``note`` adds the context
    (how the suite's value was obtained, why it differs)."""
    if not _finite(paper_value) or not _finite(suite_value):
        raise ValueError(f"claim '{id}': judge() needs finite values, got paper {paper_value!r}, "
                         f"suite {suite_value!r}")
    diff = float(suite_value) - float(paper_value)
    allowed = tolerance.allowed(float(paper_value))
    diff_text = (f"{diff:+.4g} percentage points" if unit == "%" else f"{diff:+.4g} {unit}".rstrip())
    rel = f" ({100 * diff / abs(paper_value):+.1f} % of the paper's value)" if paper_value and unit != "%" else ""
    head = (f"measured {format_value(suite_value, unit)} against the paper's {format_value(paper_value, unit)}: "
            f"{diff_text}{rel}")
    if abs(diff) <= allowed or math.isclose(abs(diff), allowed, rel_tol=1e-9):  # the edge reproduces
        kind, text = REPRODUCES, f"{head}, within the tolerance of {tolerance.describe(unit)}."
    else:
        excess = abs(diff) - allowed
        excess_text = f"{excess:.4g} percentage points" if unit == "%" else format_value(excess, unit)
        kind, text = DOES_NOT_REPRODUCE, (f"{head}, outside the tolerance of {tolerance.describe(unit)} by "
                                          f"{excess_text}.")
    return Claim(id=id, method=method, statement=statement, source=source, paper_value=float(paper_value),
                 unit=unit, suite_value=float(suite_value), suite_source=suite_source, setting=dict(setting or {}),
                 tolerance=tolerance, kind=kind, explanation=_sentence(text, note))


def at_least(id: str, statement: str, source: str, bound: float, value: float, unit: str, why: str, *,
             setting: dict | None = None, suite_source: str = "run", method: str = "", note: str = "") -> Claim:
    """A one-sided claim ("more than double", "higher with dynamic lights"): :data:`REPRODUCES` when the measured
    ``value`` is at least ``bound``, else :data:`DOES_NOT_REPRODUCE` with the shortfall. :func:`judge` compares
    two-sided, so the claim carries the bound as the paper's value and a zero absolute tolerance whose ``why`` says
    what the bound stands for. A ``value`` that is not finite (a ratio over a zero) is :data:`NOT_MEASURABLE`."""
    if not _finite(bound):
        raise ValueError(f"claim '{id}': at_least() needs a finite bound, got {bound!r}")
    if not _finite(value):
        return not_measurable(id, statement, source, f"the runs give no finite value ({value!r}) for {_clause(why)}",
                              paper_value=bound, unit=unit, setting=setting, method=method, note=note)
    ok = float(value) >= float(bound)
    text = (f"measured {format_value(value, unit)}, {'at least' if ok else 'below'} the bound "
            f"{format_value(bound, unit)} that the paper's statement implies"
            + ("" if ok else f" (short by {format_value(float(bound) - float(value), unit)})") + ".")
    return Claim(id=id, method=method, statement=statement, source=source, paper_value=float(bound), unit=unit,
                 suite_value=float(value), suite_source=suite_source, setting=dict(setting or {}),
                 tolerance=Tolerance(absolute=0.0, why=why), kind=REPRODUCES if ok else DOES_NOT_REPRODUCE,
                 explanation=_sentence(text, note))


def settled(claim: Claim, kinds_at_ends, reason: str, note: str = "") -> Claim:
    """``claim`` where the measurement's uncertainty cannot change its verdict: ``kinds_at_ends`` are the verdicts
    at the ends of the interval the measured value may lie in (judged like ``claim``); if any differs from
    ``claim``'s, the same claim as :data:`NOT_MEASURABLE`, with ``reason`` (why the interval is that wide) and
    ``note``."""
    if all(kind == claim.kind for kind in kinds_at_ends):
        return claim
    return not_measurable(claim.id, claim.statement, claim.source, reason, paper_value=claim.paper_value,
                          unit=claim.unit, setting=claim.setting, method=claim.method, note=note)


def by_calibration(id: str, statement: str, source: str, calibrated_input: str, *, paper_value=None,
                   suite_value=None, unit: str = "", setting: dict | None = None, suite_source: str = "run",
                   method: str = "", note: str = "") -> Claim:
    """The claim holds because ``calibrated_input`` (which input, and to what of the paper) was set from the
    paper: :data:`BY_CALIBRATION`. A ``suite_value`` is shown but is not evidence for the claim."""
    text = f"holds because {_clause(calibrated_input)}."
    if _finite(paper_value) and _finite(suite_value):
        text += (f" The suite's {format_value(suite_value, unit)} against the paper's "
                 f"{format_value(paper_value, unit)} follows from that calibration; it does not test the claim.")
    return Claim(id=id, method=method, statement=statement, source=source, paper_value=_number(paper_value),
                 unit=unit, suite_value=_number(suite_value), suite_source=suite_source, setting=dict(setting or {}),
                 kind=BY_CALIBRATION, explanation=_sentence(text, note))


def by_construction(id: str, statement: str, source: str, construction: str, *, paper_value=None,
                    suite_value=None, unit: str = "", setting: dict | None = None, suite_source: str = "run",
                    method: str = "", note: str = "") -> Claim:
    """The claim follows from how the suite is built (``construction`` says how): :data:`BY_CONSTRUCTION`."""
    text = f"follows from the suite's construction: {_clause(construction)}."
    return Claim(id=id, method=method, statement=statement, source=source, paper_value=_number(paper_value),
                 unit=unit, suite_value=_number(suite_value), suite_source=suite_source, setting=dict(setting or {}),
                 kind=BY_CONSTRUCTION, explanation=_sentence(text, note))


def not_measurable(id: str, statement: str, source: str, reason: str, *, paper_value=None, unit: str = "",
                   setting: dict | None = None, method: str = "", note: str = "") -> Claim:
    """The suite cannot measure the claim; ``reason`` says why (it is the explanation): :data:`NOT_MEASURABLE`,
    no suite value."""
    return Claim(id=id, method=method, statement=statement, source=source, paper_value=_number(paper_value),
                 unit=unit, setting=dict(setting or {}), kind=NOT_MEASURABLE,
                 explanation=_sentence(f"{_clause(reason)}.", note))


@dataclass(frozen=True)
class Expected:
    """A claim a method's report checks when its results hold what the check needs: the claim (``statement``,
    ``source``, ``paper_value`` in ``unit``) and ``needs``, what the check reads (which runs or bench figures)."""

    statement: str
    source: str
    needs: str
    paper_value: float | None = None
    unit: str = ""


class ClaimList:
    """The claims of one method's report, declared up front (id → :class:`Expected`), so that a claim whose runs
    are missing from the results (a scene not on this machine, a preset not run) stays in the table as
    :data:`NOT_MEASURABLE`, saying what it needs, instead of vanishing.

    ``head(id)`` gives ``(id, statement, source)``, the first arguments of :func:`judge` and its siblings, so the
    statement is written once. :meth:`complete` adds the missing claims and refuses a claim that is not declared."""

    def __init__(self, method: str, expected: dict):
        self.method, self.expected = method, dict(expected)

    def head(self, id: str) -> tuple:
        e = self.expected[id]
        return id, e.statement, e.source

    def complete(self, claims: list) -> list:
        """``claims`` plus one :data:`NOT_MEASURABLE` claim for every declared id that none of them has."""
        have = {c.id for c in claims}
        unknown = sorted(have - set(self.expected))
        if unknown:
            raise ValueError(f"method '{self.method}': claim '{unknown[0]}' is not declared in its ClaimList")
        return list(claims) + [
            not_measurable(id, e.statement, e.source, f"not in these results: {_clause(e.needs)}",
                           paper_value=e.paper_value, unit=e.unit, method=self.method)
            for id, e in self.expected.items() if id not in have]


def claims_table(claims):
    """A pandas DataFrame with one :meth:`Claim.as_row` per claim (columns :data:`ROW_COLUMNS`)."""
    import pandas as pd

    return pd.DataFrame([c.as_row() for c in claims], columns=list(ROW_COLUMNS))
