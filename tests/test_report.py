"""report.html: its numbers are metrics_history.json's, it stands alone, and Chromium renders it."""

from __future__ import annotations

import json
import subprocess
from html.parser import HTMLParser
from pathlib import Path

from tests.conftest import require_tool
from zk0.artifacts.report import REPORT_FILE, write_report
from zk0.artifacts.run_folder import History

REFUSAL = "Client 2 (c<&>): Dataset 'c<&>' records no camera."


class Tables(HTMLParser):
    """Each table's rows (cells as (text, data-value)), image sources, and every URL the page loads."""

    def __init__(self):
        super().__init__()
        self.tables, self.images, self.loads, self.text = {}, [], [], []
        self._table = self._row = self._cell = None

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "table":
            self._table = self.tables.setdefault(attrs.get("id"), [])
        elif tag == "tr" and self._table is not None:
            self._row = []
            self._table.append(self._row)
        elif tag in ("td", "th") and self._row is not None:
            self._cell = ["", attrs.get("data-value")]
            self._row.append(self._cell)
        if tag == "img":
            self.images.append(attrs["src"])
        for key in ("src", "href"):
            if key in attrs and tag != "img":
                self.loads.append(attrs[key])

    def handle_endtag(self, tag):
        if tag == "table":
            self._table = None
        elif tag in ("td", "th"):
            self._cell = None

    def handle_data(self, data):
        self.text.append(data)
        if self._cell is not None:
            self._cell[0] += data.strip()


def a_run(run_dir: Path) -> tuple[dict, dict]:
    """Three rounds written by zk0's own History (JSON and charts), one client refused in round 2."""
    history = History(run_dir, {0: "a", 1: "b", 2: "c<&>"}, {})
    history.add(0, "server-evaluate", {"policy-loss": 1.7, "action-mse": 384.15643})
    history.add(0, "wall-s", 1.2)
    history.write_round(0)
    for number, mse in ((1, 300.123456), (2, 250.5)):
        for index in (0, 1):
            history.add_client(number, "train", index, {"train-loss": 1.0 / number + index, "num-examples": 16})
            history.add_client(number, "evaluate", index, {"action-mse": mse + index, "num-examples": 32})
        history.add(number, "aggregate-train", {"train-loss": 1.0 / number + 0.5})
        history.add(number, "aggregate-evaluate", {"action-mse": mse + 0.5})
        history.add(number, "server-evaluate", {"policy-loss": 1.5 / number, "action-mse": mse})
        history.add(number, "wall-s", 10.0 * number)
        history.write_round(number)
    history.add_client(2, "train", 2, {"error": REFUSAL})
    history.write_round(2)
    config = {"num-server-rounds": 3, "server-optimiser": "nesterov", "output-dir": str(run_dir.parent)}
    return json.loads((run_dir / "server" / "metrics_history.json").read_text()), config


def test_the_reports_numbers_are_the_histories(tmp_path):
    run_dir = tmp_path / "2026-11-30_12-00-00"
    history, config = a_run(run_dir)
    best = {"round": 2, "action-mse": 250.5}
    page = Tables()
    page.feed(write_report(run_dir, history, config, best, 3).read_text())

    header, *rows = page.tables["rounds"]
    assert [c[0] for c in header][:3] == ["round", "clients trained", "refused"]
    columns = [c[0] for c in header]
    for row, record in zip(rows, history["rounds"], strict=True):
        cells = dict(zip(columns, row, strict=True))
        expected = {
            "round": record["round"],
            "train loss": record.get("aggregate-train", {}).get("train-loss"),
            "clients' action MSE": record.get("aggregate-evaluate", {}).get("action-mse"),
            "server action MSE": record["server-evaluate"]["action-mse"],
            "server policy loss": record["server-evaluate"]["policy-loss"],
            "seconds since start": record["wall-s"],
        }
        for column, value in expected.items():
            text, exact = cells[column]
            if value is None:
                assert (text, exact) == ("-", None), column
            else:
                assert float(exact) == value and text == (str(value) if isinstance(value, int) else f"{value:.4g}")
    assert [r[2][0] for r in rows] == ["0", "0", "1"], "round 2's refusal is counted"
    assert not any(c.startswith("success") for c in columns), "a column no round has is left out"

    clients = {row[1][0]: row for row in page.tables["clients"][1:]}
    assert set(clients) == {"a", "b", "c<&>"}, "names are escaped in the HTML and read back as given"
    assert [clients[name][2][0] for name in ("a", "b", "c<&>")] == ["1", "1", "2"]  # from round
    assert float(clients["a"][4][1]) == 32 and float(clients["b"][5][1]) == 1.5  # samples; last train loss
    assert clients["c<&>"][7][0] == "1"
    assert any(REFUSAL in t for t in page.text), "the refusal's own sentence is shown"
    assert dict((k[0], v[0]) for k, v in page.tables["config"])["server-optimiser"] == "nesterov"

    assert len(page.images) == 2 and all(src.startswith("data:image/png;base64,") for src in page.images)
    assert page.loads == [], "nothing is loaded from elsewhere: the page opens from disk alone"
    best_line = "".join(page.text)
    assert f"--policy.path={run_dir / 'models' / 'best'}" in best_line and "Round 2" in best_line


def test_chromium_renders_the_report_with_no_console_error(tmp_path):
    """Chromium (headless) loads the report from disk: no console message, every chart decoded to
    its real size, both tables laid out; a screenshot is taken."""
    require_tool("chromium", "chromium")
    run_dir = tmp_path / "2026-11-30_12-00-00"
    history, config = a_run(run_dir)
    report = write_report(run_dir, history, config, {"round": 2, "action-mse": 250.5}, 3)
    # A probe beside the report (not in it: the report has no script) measures what was rendered.
    probe = run_dir / "probe.html"
    probe.write_text(
        report.read_text().replace(
            "</body>",
            "<script>window.onload = () => { document.title = JSON.stringify({"
            "images: [...document.images].map(i => [i.complete, i.naturalWidth, i.naturalHeight]),"
            "rows: [...document.querySelectorAll('table')].map(t => [t.id, t.rows.length, t.offsetHeight])}); };"
            "</script></body>",
        )
    )
    # No /dev/shm (Ray's object store may hold it all while other tests run), nothing fetched in the
    # background (there is no network), console messages on stderr.
    chromium = [
        "chromium",
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--disable-background-networking",
        "--disable-component-update",
        "--no-first-run",
        f"--user-data-dir={tmp_path / 'chromium'}",
        "--enable-logging=stderr",
        "--v=0",
    ]
    dom = subprocess.run(
        [*chromium, "--dump-dom", probe.as_uri()],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    title = dom.stdout.split("<title>", 1)[1].split("</title>", 1)[0].replace("&quot;", '"')
    rendered = json.loads(title)
    assert rendered["images"] == [[True, 700, 450], [True, 700, 450]], "both charts decode at 7x4.5 in, 100 dpi"
    tables = {name: (rows, height) for name, rows, height in rendered["rows"]}
    assert tables["rounds"][0] == 4 and tables["clients"][0] == 4 and all(h > 0 for _, h in tables.values())
    shot = tmp_path / "report.png"
    loaded = subprocess.run(
        [*chromium, "--window-size=1200,1600", f"--screenshot={shot}", report.as_uri()],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    assert shot.stat().st_size > 10_000
    console = [line for line in (dom.stderr + loaded.stderr).splitlines() if "CONSOLE" in line]
    assert console == [], console


def test_each_owners_personal_model_is_shown_beside_the_global_one_with_its_command(tmp_path):
    """With personal-steps the clients' table gives each owner's personal model next to the global
    one (held-out action MSE, and success in its own conditions with the interval), and says where
    the owner's personal model is and how lerobot-rollout runs it."""
    run_dir = tmp_path / "run"
    history = History(run_dir, {0: "a", 1: "b"}, {})
    history.add(0, "server-evaluate", {"policy-loss": 1.7, "action-mse": 384.0})
    own = {"own-success-rate": 0.4, "own-success-low": 0.22, "own-success-high": 0.61, "own-episodes": 20.0}
    personal = {"personal-own-success-rate": 0.6, "personal-own-success-low": 0.39,
                "personal-own-success-high": 0.78, "personal-own-episodes": 20.0}  # fmt: skip
    for index, p in ((0, 0.4), (1, 0.01)):  # McNemar's p of the two on the same episodes
        history.add_client(1, "train", index, {"train-loss": 1.0, "num-examples": 16})
        history.add_client(
            1, "evaluate", index,
            {"action-mse": 235.5, "personal-action-mse": 199.25, **own, **personal, "personal-own-p": p},
        )  # fmt: skip
    history.add(1, "server-evaluate", {"policy-loss": 1.5, "action-mse": 300.0})
    history.write_round(1)
    snapshot = json.loads((run_dir / "server" / "metrics_history.json").read_text())
    page = Tables()
    page.feed(write_report(run_dir, snapshot, {"num-server-rounds": 1}, None, 1).read_text())
    header, *rows = page.tables["clients"]
    cells = dict(zip([c[0] for c in header], rows[0], strict=True))
    assert cells["last evaluation action MSE"] == ["235.5", "235.5"] and cells["its personal model's action MSE"] == ["199.2", "199.25"]
    assert cells["global model's success in its own conditions"] == ["40% [22, 61] of 20", "0.4"]
    assert cells["personal model's success there"] == ["60% [39, 78] of 20", "0.6"]
    choices = [dict(zip([c[0] for c in header], row, strict=True))["which model to run"][0] for row in rows]
    assert choices == [
        "run the global model (no difference beyond the noise, McNemar p 0.4)",
        "run the personal model (McNemar p 0.01)",
    ], "by success on the same episodes, though both personal models' held-out MSE is lower"
    assert any("--policy.path=clients/client_<i>/models/personal" in t for t in page.text)


def test_every_round_rewrites_the_report(tmp_path):
    """write_report replaces the page whole (temp file + rename): one report, no temp left."""
    run_dir = tmp_path / "run"
    history, config = a_run(run_dir)
    write_report(run_dir, history, config, None, 3)
    first = (run_dir / REPORT_FILE).read_text()
    assert "no <code>models/best</code>" in first
    write_report(run_dir, history, config, {"round": 1, "action-mse": 300.123456}, 3)
    assert sorted(p.name for p in run_dir.iterdir()) == ["clients", REPORT_FILE, "server"]
    assert (run_dir / REPORT_FILE).read_text() != first


def test_rollout_videos_of_the_best_and_the_latest_round_are_linked_beside_it(tmp_path):
    """With closed-loop evaluation the report shows the best and the latest round's rollouts,
    linked by a path relative to the report (the videos stay in server/videos/)."""
    run_dir = tmp_path / "run"
    history, config = a_run(run_dir)
    videos = run_dir / "server" / "videos"
    videos.mkdir()
    for number in (0, 1, 2):
        (videos / f"round_{number}.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42")
    page = Tables()
    page.feed(write_report(run_dir, history, config, {"round": 1, "action-mse": 300.123456}, 3).read_text())
    assert page.loads == ["server/videos/round_1.mp4", "server/videos/round_2.mp4"]
    assert all((run_dir / src).is_file() for src in page.loads)


def test_an_owner_lit_more_dimly_than_every_other_is_warned(tmp_path):
    """A simulated owner whose room lies beyond the other owners' span (here the left set-up lit at
    0.2, beside two owners with the left set-up as it is, lit at 0.8) is named with how its room
    differs; owners inside the span, and datasets that are not simulated, are not."""
    run_dir = tmp_path / "run"
    clients = {0: "sim-so101-left-cube", 1: "sim-so101-left-outside-dim-0-cube", 2: "sim-so101-left-cube", 3: "a"}
    history = History(run_dir, clients, {})
    for index in clients:
        history.add_client(1, "train", index, {"train-loss": 1.0, "num-examples": 16})
    history.write_round(1)
    snapshot = json.loads((run_dir / "server" / "metrics_history.json").read_text())
    page = Tables()
    page.feed(write_report(run_dir, snapshot, {"num-server-rounds": 1}, None, 1).read_text())
    text = " ".join(" ".join(page.text).split())
    assert "Client 1 (sim-so101-left-outside-dim-0-cube) is outside the span" in text
    assert "lit more dimly (0.20) than any other owner's room (0.80-0.80)" in text
    assert "Client 0" not in text and "Client 2" not in text and "Client 3" not in text


def test_an_owner_who_joined_mid_run_is_shown_from_the_round_it_joined(tmp_path):
    """Round 2's record names the client whose first reply it is (``joined``), and the clients'
    table gives each one's first round."""
    run_dir = tmp_path / "run"
    history = History(run_dir, {0: "a", 1: "b", 2: "c"}, {})
    for number, clients in ((1, (0, 1)), (2, (0, 1, 2)), (3, (0, 2))):
        for index in clients:
            history.add_client(number, "train", index, {"train-loss": 1.0, "num-examples": 16})
        history.write_round(number)
    assert "joined" not in json.loads((run_dir / "server" / "round_1.json").read_text())
    assert json.loads((run_dir / "server" / "round_2.json").read_text())["joined"] == [2]
    assert "joined" not in json.loads((run_dir / "server" / "round_3.json").read_text())
    snapshot = json.loads((run_dir / "server" / "metrics_history.json").read_text())
    page = Tables()
    page.feed(write_report(run_dir, snapshot, {"num-server-rounds": 3}, None, 3).read_text())
    header, *rows = page.tables["clients"]
    first = [c[0] for c in header].index("from round")
    assert [row[first][0] for row in rows] == ["1", "1", "2"]


def test_a_multi_task_server_set_gets_a_task_by_round_table(tmp_path):
    """Rounds whose closed-loop evaluation rolled the model out in several tasks: one row per
    evaluated round, one column per task, each cell the success with its interval and episode count
    as the JSON has it; a run of one task has no such table."""
    from zk0.learning.closed_loop import Episode, summary

    run_dir = tmp_path / "2026-12-07_12-00-00"
    history = History(run_dir, {0: "sim-so101-left-pick-place-cube"}, {})
    for number, wins in ((0, {"pick": 0, "sort": 0}), (1, {"pick": 3, "sort": 1})):
        episodes = [
            Episode(seed, kind, seed < wins[kind], False, False, False, 10, actions=None)
            for kind in ("pick", "sort") for seed in range(4)
        ]  # fmt: skip
        history.add(number, "server-evaluate", {"action-mse": 10.0 - number, **summary(episodes)})
        history.write_round(number)
    recorded = json.loads((run_dir / "server" / "metrics_history.json").read_text())
    assert recorded["rounds"][1]["server-evaluate"]["sort-success-rate"] == 0.25
    page = Tables()
    page.feed(write_report(run_dir, recorded, {}, {"round": 1, "action-mse": 9.0}, 1).read_text())
    header, *rows = page.tables["tasks"]
    assert [c[0] for c in header] == ["round", "pick", "sort"]
    assert [[c[0] for c in row] for row in rows] == [
        ["0", "0% [0, 49] of 4", "0% [0, 49] of 4"],
        ["1", "75% [30, 95] of 4", "25% [5, 70] of 4"],
    ]
    assert float(rows[1][1][1]) == 0.75
    one_task, _ = a_run(tmp_path / "one")
    page = Tables()
    page.feed(write_report(tmp_path / "one", one_task, {}, None, 3).read_text())
    assert "tasks" not in page.tables
