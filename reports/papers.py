"""The papers the methods reproduce, named as a reader cites them (author, title, year, where), from their
title pages in the shared seed texts. The report shows these instead of the suite's internal seed numbers."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Paper:
    authors: tuple  # each author as the title page writes the name
    surname: str  # the first author's family name, for short citations
    title: str
    year: str
    venue: str

    def cite(self) -> str:
        """"Authors (year). Title. Venue." """
        names = ", ".join(self.authors[:-1]) + (" and " if len(self.authors) > 1 else "") + self.authors[-1]
        return f"{names} ({self.year}). {self.title}. {self.venue}."

    def short(self) -> str:
        """"Surname year" or "Surname et al. year", for table cells and headings."""
        return f"{self.surname}{' et al.' if len(self.authors) > 1 else ''} {self.year}"


# Method folder -> the paper it reproduces. Baselines (video_stream, local_direct) have none.
PAPERS = {
    "visibility_bitmap": Paper(("Kim-Chan Tze Hui, Louiz",), "Kim-Chan", "Hardware Ray-Tracing Assisted Hybrid "
                               "Rendering Pipeline for Games", "2021", "B.Comp. dissertation, National University of "
                               "Singapore (advisor Anand Bhojan)"),
    "quake_drt": Paper(("Bauer",), "Bauer", "[title page not in the stored text: a thesis on real-time "
                       "distribution ray tracing in the Quake III engine with NVIDIA RTX]",
                       "2020", "Diploma thesis, TU Wien"),
    "layered_pvs": Paper(("Jaroslav Kravec",), "Kravec", "Realistic Remote Rendering for VR and Mobile Devices",
                         "2020", "Master's thesis, Czech Technical University in Prague (supervisor Jiří Bittner)"),
    "rail": Paper(("Keith Bugeja", "Kurt Debattista", "Sandro Spina"), "Bugeja", "An asynchronous method for "
                  "cloud-based rendering", "2019", "The Visual Computer (author's accepted manuscript, WRAP 108585)"),
}


def paper_of(method: str) -> Paper | None:
    return PAPERS.get(method)


def method_title(method: str) -> str:
    """"visibility_bitmap — Kim-Chan Tze Hui 2021" or the bare name for a baseline."""
    paper = paper_of(method)
    return f"{method} — {paper.short()}" if paper else f"{method} (baseline)"
