"""`mehs report` — HTML report of a dataset folder or of an evaluation results folder."""

from __future__ import annotations


def configure(parser):
    parser.add_argument("folder", metavar="FOLDER",
                        help="a dataset folder (manifest.json, from 'mehs build') or an "
                             "evaluation results folder (from 'mehs evaluate --out')")
    parser.add_argument("--out", "-o", metavar="HTML", default=None,
                        help="HTML file to write (default FOLDER/report.html; images go to "
                             "<name>_files/ beside it)")


def run(args):
    from pathlib import Path

    from mehs.dataset.report import write_report
    from mehs.errors import InputError

    if not Path(args.folder).exists():
        raise InputError("no such folder (give a dataset folder or an evaluation results "
                         "folder)", args.folder)
    out = write_report(args.folder, args.out)
    print(out)
    return 0
