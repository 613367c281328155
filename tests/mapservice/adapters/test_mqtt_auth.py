"""Mosquitto's password file and ACL as `mapservice robot add/remove` write them."""

from __future__ import annotations

import shutil
import stat
import subprocess
from concurrent.futures import ThreadPoolExecutor

import pytest

from mapservice.adapters.mqtt_auth import (
    GATEWAY_USER,
    PROCESSORS_USER,
    AclTopics,
    BrokerFiles,
    hash_password,
    legacy_robots_in,
    read_password_file,
    render_acl,
    verify_password,
)
from mapservice.settings import Settings


def test_hash_is_what_mosquitto_passwd_writes_and_reads(tmp_path):
    """Our $7$ hash verifies a password mosquitto_passwd hashed, and the other way round
    (mosquitto_passwd -U is not needed: Mosquitto itself reads ours in the integration test)."""
    ours = hash_password("s3cret")
    assert ours.startswith("$7$101$") and verify_password("s3cret", ours)
    assert not verify_password("wrong", ours) and not verify_password("s3cret", "garbage")
    binary = shutil.which("mosquitto_passwd")
    if binary is None:
        pytest.skip("mosquitto_passwd is not installed (make test installs mosquitto)")
    path = tmp_path / "passwd"
    path.touch()
    subprocess.run([binary, "-b", str(path), "alice", "s3cret"], check=True)
    subprocess.run([binary, "-H", "sha512", "-b", str(path), "bob", "0ld"], check=True)
    users = read_password_file(path)
    assert verify_password("s3cret", users["alice"]) and not verify_password(
        "other", users["alice"]
    )
    assert verify_password("0ld", users["bob"])  # Mosquitto 1.x's $6$


def test_acl_lets_robots_publish_only_as_themselves():
    """The ACL: %u patterns for the robots' pose and chunk topics, read on advertisements, the
    gateway reading all robot topics, the processors writing advertisements, and the 2019
    chunk topic only for the robots named in its section."""
    topics = AclTopics.from_settings(Settings())
    text = render_acl(topics, ["old-7", "old-3"])
    lines = text.splitlines()
    assert "pattern write iot/coordinates/%u" in lines
    assert "pattern write iot/chunks/create/%u" in lines
    assert "pattern read iot/chunks/advertisement" in lines
    assert "pattern read iot/zones/advertisement" in lines  # robots learn the operators' zones
    gateway = lines[
        lines.index(f"user {GATEWAY_USER}") + 1 : lines.index(f"user {PROCESSORS_USER}")
    ]
    assert {
        "topic read iot/coordinates/#",
        "topic read iot/chunks/create/+",
        "topic read iot/chunks/create",
        "topic read uagv/+/+/+/state",
    } <= set(gateway)
    processors = lines[lines.index(f"user {PROCESSORS_USER}") + 1 :]
    assert {"topic write iot/chunks/advertisement", "topic write iot/zones/advertisement"} <= set(
        processors
    )
    # Nothing but the named robots may write the 2019 topic, and no line grants write on a
    # wildcard to everyone.
    assert [line for line in lines if line.endswith(" iot/chunks/create") and "write" in line] == [
        "topic write iot/chunks/create"
    ] * 2
    assert legacy_robots_in(text) == ["old-3", "old-7"]
    assert not any(line.startswith("pattern write") and "#" in line for line in lines)


def test_acl_follows_configured_topics():
    """Custom topic settings are what the ACL talks about."""
    topics = AclTopics.from_settings(
        Settings(
            coordinate_topic="site1/robots/#",
            robot_chunk_topic="site1/chunks/+",
            create_chunk_topic="site1/chunks",
            advertisement_topic="site1/adverts",
            robot_topic_root="site1/own",
            zone_advertisement_topic="site1/zones",
        )
    )
    assert topics.robot_topics("r1") == {
        "pose": "site1/robots/r1",
        "chunks": "site1/chunks/r1",
        "advertisements": "site1/adverts",
        "areaAdvertisements": "site1/adverts/area/+/+",
        "commands": "site1/own/r1/commands",
        "commandEvents": "site1/own/r1/command-events",
    }
    text = render_acl(topics)
    assert "pattern write site1/robots/%u" in text and "topic read site1/chunks" in text
    assert "pattern read site1/own/%u/commands" in text
    assert "pattern write site1/own/%u/command-events" in text
    assert (
        "topic write site1/own/+/commands" in text
        and "topic read site1/own/+/command-events" in text
    )
    assert "pattern read site1/zones" in text and "topic write site1/zones" in text
    assert "pattern read site1/adverts/area/+/+" in text
    assert "topic write site1/adverts/area/+/+" in text


def test_gateway_may_send_vda_vehicles_instant_actions():
    """The gateway delivers operators' commands to VDA 5050 vehicles as instantActions."""
    text = render_acl(AclTopics.from_settings(Settings(vda5050_interface="site1agv")))
    gateway = text.split("user mapservice-gateway\n")[1].split("\n\n")[0]
    assert "topic write site1agv/+/+/+/instantActions" in gateway.splitlines()
    assert "topic write site1agv/+/+/+/order" not in gateway


def test_add_rotate_remove_and_legacy(tmp_path):
    """add gives a fresh password (hash stored, 0600), refuses a second add without rotate,
    rotate changes the password, --legacy-chunks puts the robot in the ACL's 2019 section,
    remove takes it out of both files."""
    files = BrokerFiles.in_data_dir(tmp_path)
    first = files.add_robot("r1")
    assert first.username == first.robot_id == "r1" and len(first.password) >= 32
    assert first.topics["chunks"] == "iot/chunks/create/r1"
    hashed = read_password_file(files.password_file)["r1"]
    assert (
        verify_password(first.password, hashed)
        and first.password not in files.password_file.read_text()
    )
    assert stat.S_IMODE(files.password_file.stat().st_mode) == 0o600
    with pytest.raises(ValueError, match="--rotate"):
        files.add_robot("r1")
    second = files.add_robot("r1", rotate=True, legacy_chunks=True)
    assert second.password != first.password
    assert verify_password(second.password, read_password_file(files.password_file)["r1"])
    assert files.legacy_robots() == ["r1"] and files.robots() == ["r1"]
    files.add_robot("r1", rotate=True)  # rotating without the flag closes the 2019 topic again
    assert files.legacy_robots() == []
    files.add_robot("r2", legacy_chunks=True)
    assert files.remove_robot("r2") and not files.remove_robot("r2")
    assert files.robots() == ["r1"] and files.legacy_robots() == []


@pytest.mark.parametrize(
    "bad",
    ["", "a" * 65, "has space", "wild#card", "plus+", "a/b/c", "a/", GATEWAY_USER, PROCESSORS_USER],
)
def test_robot_ids_follow_the_gateway_rule(tmp_path, bad):
    """A robot's username is a valid robotId (no MQTT wildcards or slashes for %u) and not a
    service user's name; one slash only between a VDA 5050 vehicle's two names."""
    with pytest.raises(ValueError):
        BrokerFiles.in_data_dir(tmp_path).add_robot(bad)


def test_service_users_are_not_robots(tmp_path):
    """Service users' passwords live in the same file but are not listed as robots."""
    files = BrokerFiles.in_data_dir(tmp_path)
    files.set_service_user(GATEWAY_USER, "gw")
    files.add_robot("r1")
    assert files.robots() == ["r1"]
    assert verify_password("gw", read_password_file(files.password_file)[GATEWAY_USER])
    with pytest.raises(ValueError):
        files.set_service_user("r1", "x")


def test_concurrent_adds_lose_nobody(tmp_path):
    """Robots added at the same time (two operators, a script) all end up in the file."""
    files = BrokerFiles.in_data_dir(tmp_path)
    with ThreadPoolExecutor(8) as pool:
        list(pool.map(lambda i: BrokerFiles.in_data_dir(tmp_path).add_robot(f"r{i}"), range(40)))
    assert sorted(files.robots()) == sorted(f"r{i}" for i in range(40))


def test_rewritten_files_keep_their_mode(tmp_path):
    """A password file the operator made readable for the broker's user (e.g. 0640) keeps that
    mode when `robot add` rewrites it; a new one is 0600."""
    files = BrokerFiles.in_data_dir(tmp_path)
    files.add_robot("r1")
    assert stat.S_IMODE(files.password_file.stat().st_mode) == 0o600
    files.password_file.chmod(0o640)
    files.add_robot("r2")
    assert stat.S_IMODE(files.password_file.stat().st_mode) == 0o640


def test_vda_5050_vehicles_are_users_named_by_their_topic_levels(tmp_path):
    files = BrokerFiles(tmp_path / "passwd", tmp_path / "acl")
    cred = files.add_robot("Robo Co/7-2")
    assert cred.topics["robotId"] == "Robo@20Co:7-2"
    assert cred.topics["publishes"].startswith("uagv/<v2|v3>/Robo Co/7-2/")
    acl = files.acl_file.read_text()
    for sub in ("state", "visualization", "connection", "factsheet"):
        assert f"pattern write uagv/+/%u/{sub}\n" in acl
    assert "pattern read uagv/+/%u/order\n" in acl and "pattern write uagv/+/%u/order" not in acl
    assert files.robots() == ["Robo Co/7-2"]
    # A level that is no single topic level, a ':' (the password file's separator), a
    # wildcard, or a robot id over 64 characters: refused, saying why.
    for bad in ("Acme/7:2", "a/b/c", "Acme/+", "#/1", "/001", "M" * 40 + "/" + "S" * 30):
        with pytest.raises(ValueError, match="VDA 5050 vehicle"):
            files.add_robot(bad)
    with pytest.raises(ValueError, match="legacy-chunks"):
        files.add_robot("Acme/001", legacy_chunks=True)
