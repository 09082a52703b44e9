"""Regenerate the book's recorded ADS-B flights, ``data/adsb/<group>/<name>.csv.gz``.

Source: the sample flights recorded by The OpenSky Network and shipped inside the wheel of
the ``traffic`` package, version 2.13 (MIT licence), as ``traffic/data/samples/<group>/<name>.json.gz``.
``traffic`` itself is not imported (not a dependency): the wheel is opened with ``zipfile``,
each sample read with ``gzip`` + ``json``, converted to SI units and written as one gzipped CSV
per flight. Usage, from the repository root::

    python data/adsb/extract.py                      # pip download traffic==2.13 --no-deps
    python data/adsb/extract.py --wheel PATH.whl     # a wheel already downloaded
    python data/adsb/extract.py --out DIR            # write under DIR instead of data/adsb

Also one time window of ``collections/quickstart`` (213 aircraft recorded around Paris on
2021-10-07, 12:00-15:00 UTC, 1 s state vectors), the ground truth of the multi-target chapter:
the airborne records (``onground`` false) of every aircraft between :data:`TRAFFIC_WINDOW` (unix
seconds, start included, end excluded), in file order, written to ``traffic/<name>.csv.gz`` with
an ``icao24`` and a ``callsign`` column before the flight columns. No other ``collections`` sample
(``switzerland``, ``savan``) is read.

Every record of a flight sample is kept, in file order, bad ones included (NaN for a missing or
non-numeric field); the loader :func:`kftrack.adsb.load_flight` skips and counts bad rows.
Output is deterministic: fixed float formats and gzip with ``mtime=0`` and no file name, so a
fresh extraction equals the committed files (same text; the same bytes with the same zlib).
Only the standard library is used.
"""
from __future__ import annotations

import argparse
import gzip
import hashlib
import io
import json
import math
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

WHEEL_NAME = "traffic-2.13-py3-none-any.whl"
WHEEL_SHA256 = "5e0cd61d931d03103294361542188f08f959a55e862d5cba80ab61291021e66c"
SAMPLES = "traffic/data/samples/"

CHAPTER = ("calibration/toulouse", "calibration/munich", "calibration/london_heathrow", "calibration/lisbon",
           "gliders/alpi_italiane", "gliders/cevennes", "featured/belevingsvlucht")
NOISY = ("noisy/noisy_landing", "noisy/noisy_spoofing", "noisy/noisy_time_issue", "noisy/noisy_takeoff",
         "noisy/noisy_ground")
UNSEEN_GROUPS = ("calibration", "gliders")  # unseen = every other sample of these groups

COLUMNS = ("t_s", "lat_deg", "lon_deg", "alt_m", "groundspeed_mps", "track_deg", "vertical_rate_mps")
TRAFFIC_SAMPLE = "collections/quickstart"
TRAFFIC_NAME = "traffic/quickstart_1400"                # data/adsb/traffic/quickstart_1400.csv.gz
TRAFFIC_WINDOW = (1633615201, 1633616401)              # 2021-10-07 14:00:01 to 14:20:01 UTC (on the 1 s grid)
TRAFFIC_COLUMNS = ("icao24", "callsign") + COLUMNS
FT = 0.3048                 # m per foot (exact)
KT = 1852.0 / 3600.0        # m/s per knot (exact)
FPM = 0.3048 / 60.0         # m/s per ft/min (exact)


def get_wheel(directory: Path) -> Path:
    """``pip download traffic==2.13 --no-deps`` into ``directory``; the wheel's path."""
    cmd = [sys.executable, "-m", "pip", "download", "traffic==2.13", "--no-deps", "--only-binary", ":all:",
           "--disable-pip-version-check", "-q", "-d", str(directory)]
    res = subprocess.run(cmd, capture_output=True, text=True)
    wheel = directory / WHEEL_NAME
    if res.returncode != 0 or not wheel.is_file():
        raise RuntimeError(f"'{' '.join(cmd)}' failed (exit {res.returncode}):\n{res.stderr}")
    return wheel


def check_wheel(wheel: Path) -> None:
    """Raise if ``wheel`` is not the traffic 2.13 wheel the committed files came from."""
    digest = hashlib.sha256(wheel.read_bytes()).hexdigest()
    if digest != WHEEL_SHA256:
        raise RuntimeError(f"{wheel} has sha256 {digest}, expected {WHEEL_SHA256} ({WHEEL_NAME} on PyPI)")


def flight_names(wheel: zipfile.ZipFile) -> dict[str, tuple[str, ...]]:
    """The three sets: ``chapter``, ``noisy`` and ``unseen`` (every other calibration/glider sample)."""
    present = sorted(n[len(SAMPLES):-len(".json.gz")] for n in wheel.namelist()
                     if n.startswith(SAMPLES) and n.endswith(".json.gz"))
    missing = [n for n in CHAPTER + NOISY if n not in present]
    if missing:
        raise RuntimeError(f"samples missing from the wheel: {missing}")
    unseen = tuple(n for n in present if n.split("/")[0] in UNSEEN_GROUPS and n.count("/") == 1
                   and n not in CHAPTER)
    return {"chapter": CHAPTER, "noisy": NOISY, "unseen": unseen}


def records(raw) -> list[dict]:
    """The records of a sample, in file order: a JSON list of records, or pandas' column
    orientation ``{column: {row: value}}`` (rows in the order of the first column)."""
    if isinstance(raw, list):
        return [r if isinstance(r, dict) else {} for r in raw]
    columns = list(raw)
    rows = list(raw[columns[0]]) if columns else []
    return [{c: raw[c].get(i) for c in columns} for i in rows]


def number(value) -> float:
    """``value`` as a float; NaN if missing, boolean or not a number."""
    if value is None or isinstance(value, bool):
        return math.nan
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def fmt(x: float, spec: str | None) -> str:
    """Fixed formatting: ``nan``/``inf``/``-inf``, else ``spec % x`` (``repr`` when ``spec`` is None,
    which keeps the recorded digits of a degree value)."""
    if math.isnan(x):
        return "nan"
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return repr(x) if spec is None else spec % x


def convert(name: str, raw) -> tuple[str, dict]:
    """CSV text of one sample and a summary; one aircraft (the icao24 with most records) kept."""
    recs = records(raw)
    counts: dict = {}
    for r in recs:
        counts[r.get("icao24")] = counts.get(r.get("icao24"), 0) + 1
    icao = max(counts, key=lambda k: counts[k]) if counts else None  # ties: the first seen
    kept = [r for r in recs if r.get("icao24") == icao]
    geometric = any("geoaltitude" in r for r in kept)
    alt_key, alt_kind = ("geoaltitude", "geometric (geoaltitude, ft)") if geometric else \
        ("altitude", "barometric (altitude, ft)")
    callsigns: list = []
    for r in kept:
        c = r.get("callsign")
        if isinstance(c, str) and c.strip() and c.strip() not in callsigns:
            callsigns.append(c.strip())
    lines = [f"# kftrack ADS-B flight {name}: OpenSky Network state vectors, sample "
             f"{SAMPLES}{name}.json.gz of {WHEEL_NAME} (sha256 {WHEEL_SHA256[:16]}...; traffic is MIT)",
             f"# aircraft icao24 {icao} callsign {' '.join(callsigns) or '-'}; {len(kept)} records in file order, "
             f"none dropped" + (f"; {len(recs) - len(kept)} records of {len(counts) - 1} other aircraft dropped"
                                if len(counts) > 1 else ""),
             f"# units: t_s unix s; degrees; alt_m = {alt_kind} * 0.3048; groundspeed kt * 1852/3600; "
             "track deg as recorded; vertical_rate ft/min * 0.00508; nan = missing",
             ",".join(COLUMNS)]
    for r in kept:
        row = (fmt(number(r.get("timestamp")) / 1000.0, "%.3f"),
               fmt(number(r.get("latitude")), None), fmt(number(r.get("longitude")), None),
               fmt(number(r.get(alt_key)) * FT, "%.4f"), fmt(number(r.get("groundspeed")) * KT, "%.4f"),
               fmt(number(r.get("track")), None), fmt(number(r.get("vertical_rate")) * FPM, "%.5f"))
        lines.append(",".join(row))
    summary = {"icao24": icao, "records": len(kept), "dropped_other_aircraft": len(recs) - len(kept),
               "aircraft": len(counts), "altitude": alt_kind}
    return "\n".join(lines) + "\n", summary


def convert_traffic(raw) -> tuple[str, dict]:
    """CSV text of the airborne records of ``collections/quickstart`` inside :data:`TRAFFIC_WINDOW`.

    Airborne: the record's ``onground`` flag is ``False`` (the aircraft sends airborne, not
    surface, position messages). Formats: time in whole seconds (the sample's timestamps are whole
    seconds), latitude/longitude to 1e-5 degree (1.1 m north, 0.7 m east; below the 5 m quantum of
    the airborne CPR position encoding), altitude to 1 m (the barometric altitude's quantum is
    25 ft = 7.6 m), ground speed to 0.01 m/s (recorded in whole knots), track to 0.01 degree,
    vertical rate to 0.01 m/s (recorded in multiples of 64 ft/min = 0.33 m/s).
    """
    recs = records(raw)
    t_a, t_b = TRAFFIC_WINDOW
    kept = [r for r in recs if r.get("onground") is False and t_a <= number(r.get("timestamp")) / 1000.0 < t_b]
    aircraft = []
    for r in kept:
        if r.get("icao24") not in aircraft:
            aircraft.append(r.get("icao24"))
    lines = [f"# kftrack ADS-B traffic {TRAFFIC_NAME}: OpenSky Network state vectors, sample "
             f"{SAMPLES}{TRAFFIC_SAMPLE}.json.gz of {WHEEL_NAME} (sha256 {WHEEL_SHA256[:16]}...; traffic is MIT)",
             f"# window unix [{t_a}, {t_b}) s = 2021-10-07 14:00:01-14:20:01 UTC; airborne records (onground false) "
             f"only, in file order: {len(kept)} records of {len(aircraft)} aircraft, out of {len(recs)} records",
             "# units: t_s unix s; degrees (5 decimals); alt_m = barometric altitude ft * 0.3048; groundspeed "
             "kt * 1852/3600; track deg clockwise from north; vertical_rate ft/min * 0.00508; nan = missing",
             ",".join(TRAFFIC_COLUMNS)]
    for r in kept:
        callsign = r.get("callsign")
        callsign = callsign.strip() if isinstance(callsign, str) else ""
        row = (str(r.get("icao24")), callsign.replace(",", " "),
               fmt(number(r.get("timestamp")) / 1000.0, "%.0f"),
               fmt(number(r.get("latitude")), "%.5f"), fmt(number(r.get("longitude")), "%.5f"),
               fmt(number(r.get("altitude")) * FT, "%.0f"), fmt(number(r.get("groundspeed")) * KT, "%.2f"),
               fmt(number(r.get("track")), "%.2f"), fmt(number(r.get("vertical_rate")) * FPM, "%.2f"))
        lines.append(",".join(row))
    summary = {"icao24": f"{len(aircraft)} aircraft", "records": len(kept), "aircraft": len(aircraft),
               "altitude": "barometric (altitude, ft)"}
    return "\n".join(lines) + "\n", summary


def gzip_bytes(text: str) -> bytes:
    """Deterministic gzip of ``text`` (UTF-8; no file name, mtime 0, level 9)."""
    buf = io.BytesIO()
    with gzip.GzipFile(filename="", mode="wb", fileobj=buf, mtime=0, compresslevel=9) as fh:
        fh.write(text.encode("utf-8"))
    return buf.getvalue()


def extract(wheel: Path, out: Path) -> dict[str, dict]:
    """Write every flight of the three sets and the traffic window under ``out``; a summary per file."""
    check_wheel(wheel)
    summaries = {}
    with zipfile.ZipFile(wheel) as zf:
        sets = flight_names(zf)
        for set_name, names in sets.items():
            for name in names:
                raw = json.loads(gzip.decompress(zf.read(f"{SAMPLES}{name}.json.gz")))
                text, summary = convert(name, raw)
                path = out / f"{name}.csv.gz"
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(gzip_bytes(text))
                summaries[name] = dict(summary, set=set_name, bytes=path.stat().st_size)
        raw = json.loads(gzip.decompress(zf.read(f"{SAMPLES}{TRAFFIC_SAMPLE}.json.gz")))
        text, summary = convert_traffic(raw)
        path = out / f"{TRAFFIC_NAME}.csv.gz"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(gzip_bytes(text))
        summaries[TRAFFIC_NAME] = dict(summary, set="traffic", bytes=path.stat().st_size)
    return summaries


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--wheel", type=Path, help=f"path of {WHEEL_NAME} (default: pip download it)")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent,
                        help="output folder (default: data/adsb next to this script)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        wheel = args.wheel if args.wheel is not None else get_wheel(Path(tmp))
        summaries = extract(wheel, args.out)
    total = sum(s["bytes"] for s in summaries.values())
    for name, s in summaries.items():
        print(f"{s['set']:8s} {name:32s} {s['records']:6d} records  icao24 {s['icao24']}  "
              f"{s['bytes']:7d} bytes  alt {s['altitude']}")
    print(f"{len(summaries) - 1} flights and 1 traffic window, {total} bytes in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
