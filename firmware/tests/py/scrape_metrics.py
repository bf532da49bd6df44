#!/usr/bin/env python3
"""Scrapes an irtrackd /metrics URL and parses it with prometheus_client's strict OpenMetrics
parser (an implementation independent of the Rust encoder). Prints one JSON document: the
samples as {"name", "labels", "value"} and the families' types, or {"error": ...} when the text
does not parse."""

import json
import sys
import urllib.request

from prometheus_client.openmetrics.parser import text_string_to_metric_families


def main() -> None:
    url = sys.argv[1]
    with urllib.request.urlopen(url, timeout=5) as resp:
        text = resp.read().decode("utf-8")
    try:
        families = list(text_string_to_metric_families(text))
    except Exception as e:  # the parser raises ValueError and others on bad text
        print(json.dumps({"error": f"{type(e).__name__}: {e}"}), flush=True)
        return
    samples = []
    types = {}
    for fam in families:
        types[fam.name] = fam.type
        for s in fam.samples:
            samples.append({"name": s.name, "labels": dict(s.labels), "value": s.value})
    print(json.dumps({"samples": samples, "types": types}), flush=True)


if __name__ == "__main__":
    main()
