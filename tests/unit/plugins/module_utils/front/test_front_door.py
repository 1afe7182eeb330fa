"""The front door's settings and files (module_utils/front/front_door.py)."""

from __future__ import annotations

import json

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_auth, front_door, pool

CODE = {"auth": "CODE", "store": "STORE", "api": "API", "pool": "POOL"}
HASH = door_auth.hash_password("pw", 10000, b"0123456789abcdef")
GOOD = {
    "server_name": "fleet.lab",
    "port": 443,
    "http_port": 80,
    "auth_port": 9480,
    "api_port": 9481,
    "login_rate": "10r/m",
    "session_hours": 8,
    "users": [{"name": "olga", "role": "operator", "password_hash": HASH}],
    "backends": [{"name": "gpu-1", "status_url": "http://10.0.0.5:8290/status"}],
    "viewer_port_base": 20000,
}
VIEWERS = dict(
    GOOD,
    backends=[
        {
            "name": "gpu-1",
            "status_url": "http://10.0.0.5:8290/status",
            "viewers": [{"instance": 0, "page": "http://10.0.0.5:8210/", "signal": "10.0.0.5:49100"}],
        },
        {
            "name": "gpu-2",
            "status_url": "http://10.0.0.6:8290/status",
            "viewers": [
                {"instance": n, "page": f"http://10.0.0.{10 + n}:8210/", "signal": f"10.0.0.{10 + n}:49100"}
                for n in (0, 3)
            ],
        },
    ],
)


def test_good_settings_pass():
    assert front_door.check(GOOD) == []
    assert front_door.check(dict(GOOD, port="8443", http_port="0")) == []


@pytest.mark.parametrize(
    "over, start",
    [
        ({"server_name": "fleet lab"}, "front_door_server_name: 'fleet lab'"),
        # nothing but the name goes into the configuration files (no IPv6 scope, no second line)
        ({"server_name": "fe80::1%eth0;"}, "front_door_server_name: 'fe80::1%eth0;'"),
        ({"server_name": "fleet.lab\n"}, "front_door_server_name: 'fleet.lab\\n'"),
        ({"port": 70000}, "front_door_port: 70000 is not a port"),
        ({"auth_port": 80}, "front_door_auth_port: 80 is not a port of 1024-65535"),
        ({"http_port": 443}, "front_door_port and front_door_http_port: both 443"),
        ({"login_rate": "10/m"}, "front_door_login_rate: '10/m'"),
        ({"session_hours": 0}, "front_door_session_hours: 0"),
        ({"metrics_dir": "var/lib/x"}, "front_door_metrics_textfile_dir: 'var/lib/x' is not an absolute path"),
        ({"sim": {"limits": {"olga": 2}}}, "front_door_sim_limits: 'olga' is neither user:NAME nor role:ROLE"),
        ({"sim": {"limits": {"role:operator": -1}}}, "front_door_sim_limits: role:operator: -1 is not a whole number"),
        ({"sim": {"per_person": 0}}, "front_door_sim_per_person: 0 is not a whole number of 1-100"),
        ({"sim": {"max_minutes": "2h"}}, "front_door_sim_max_minutes: '2h' is not a whole number"),
        ({"sim": {"queue_grace_s": 5}}, "front_door_sim_queue_grace_seconds: 5 is not a whole number of 10-86400"),
        ({"sim": {"max_minutes": 10, "warn_minutes": 10}}, "front_door_sim_warn_minutes: 10 is not below"),
        ({"sim": {"files_mib": -1}}, "front_door_sim_files_mib: -1 is not a whole number of 0-102400. Fix: e.g. 1024."),
        ({"sim": {"files_dir": "files"}}, "front_door_sim_files_dir: 'files' is not an absolute path"),
        ({"sim": {"files_dir": "/srv/../etc"}}, "front_door_sim_files_dir: '/srv/../etc' is not an absolute path"),
        ({"sim": {"files_dir": "/srv"}}, "front_door_sim_files_dir: '/srv' is not an absolute path of two or more"),
        (
            {"sim": {"files_dir": "/var/lib/isaac-sim-front-door"}},
            "front_door_sim_files_dir: /var/lib/isaac-sim-front-door is the",
        ),
        (
            {"sim": {"files_dir": "/etc/isaac-sim/front-door/f"}},
            "front_door_sim_files_dir: /etc/isaac-sim/front-door/f is the",
        ),
        ({"users": []}, "front_door_users: empty"),
        (
            {"users": [{"name": "olga", "role": "admin", "password_hash": HASH}]},
            "front_door_users[0] (olga): role 'admin'",
        ),
        (
            {"users": [{"name": "olga", "role": "viewer", "password": "pw", "password_hash": HASH}]},
            "front_door_users[0] (olga): has a plain password",
        ),
        (
            {"users": [{"name": "olga", "role": "viewer", "password_hash": "pw"}]},
            "front_door_users[0] (olga): password_hash is not a PBKDF2-SHA256 hash",
        ),
        ({"users": [GOOD["users"][0], GOOD["users"][0]]}, "front_door_users[1] (olga): named twice"),
        ({"users": [{"name": "a b", "role": "viewer", "password_hash": HASH}]}, "front_door_users[0] (a b): the name"),
        (
            {"backends": [{"name": "a/b", "status_url": "http://x/status"}]},
            "front_door_hosts: the inventory host 'a/b'",
        ),
        (
            {"backends": [{"name": "gpu-1", "status_url": "http://10.0.0.5:8290/status; return 200"}]},
            "front_door_hosts: gpu-1 says its status endpoint is at",
        ),
        ({"unread": ["gpu-2"]}, "front_door_hosts: gpu-2 did not say where they serve their status"),
        ({"viewer_port_base": 80}, "front_door_viewer_port_base: 80 is not a port of 1024-65535"),
        (
            {"backends": [dict(VIEWERS["backends"][0], viewers=[{"instance": 100, "page": "x", "signal": "y"}])]},
            "front_door_hosts: gpu-1 instance 100: the front door serves viewers of instances 0-99",
        ),
        (
            {
                "backends": [
                    dict(VIEWERS["backends"][0], viewers=[{"instance": 1, "page": "http://a b/", "signal": "y"}])
                ]
            },
            "front_door_hosts: gpu-1 instance 1: its viewer at 'http://a b/'",
        ),
        (
            {
                "viewer_port_base": 65533,
                "backends": [dict(VIEWERS["backends"][1], viewers=VIEWERS["backends"][1]["viewers"][1:])],
            },
            "front_door_viewer_port_base: 65533 gives front_door_hosts: gpu-2 instance 3 port 65536",
        ),
        (
            {"viewer_port_base": 9480, "backends": VIEWERS["backends"][:1]},
            "front_door_viewer_port_base: 9480 gives front_door_hosts: gpu-1 instance 0 port 9480, which "
            "front_door_auth_port already takes",
        ),
        (
            {"client_ca_path": "/tmp/no-such.pem", "client_ca": None},
            "front_door_client_ca: '/tmp/no-such.pem' is not a file on the controller. Fix:",
        ),
        (
            {"client_ca_path": "/etc/hosts", "client_ca": "127.0.0.1 localhost"},
            "front_door_client_ca: '/etc/hosts' holds no PEM certificate. Fix:",
        ),
    ],
)
def test_each_bad_setting_is_named_with_its_fix(over, start):
    errors = front_door.check(dict(GOOD, **over))
    assert len(errors) == 1 and errors[0].startswith(start) and "Fix:" in errors[0], errors


def test_nginx_serves_tls_only_behind_the_login_and_redirects_plain_http():
    conf = front_door.nginx_conf(GOOD, "managed")
    assert "ssl_protocols TLSv1.2 TLSv1.3;" in conf and 'Strict-Transport-Security "max-age=31536000" always' in conf
    # to the configured name, never the client's Host header
    assert "listen 80;\n    listen [::]:80;\n    return 301 https://fleet.lab$request_uri;" in conf
    # only login attempts count against the rate
    assert 'map $request_method $fleet_login_key { POST $binary_remote_addr; default ""; }' in conf
    assert "limit_req_zone $fleet_login_key zone=fleet_login:1m rate=10r/m;" in conf
    assert f"ssl_ciphers {front_door.CIPHERS};" in conf and "ssl_session_tickets off;" in conf
    assert "add_header X-Frame-Options DENY always;" in conf
    # nothing behind the login is kept in a browser's cache (a logout would leave the page there)
    assert conf.count('add_header Cache-Control "no-store" always;') == conf.count("ssl_certificate ") >= 1
    backend = conf.split("location = /hosts/gpu-1/status {", 1)[1].split("}", 1)[0]
    assert "auth_request /fleet-auth;" in backend and "proxy_pass http://10.0.0.5:8290/status;" in backend
    # the session never travels to the hosts behind (plain HTTP)
    assert 'proxy_set_header Cookie "";' in backend and 'proxy_set_header Authorization "";' in backend
    # operators' paths: nginx's own match asks the question that needs the role
    operator = conf.split("    location /operator/ {", 1)[1].split("}", 1)[0]
    assert "auth_request /fleet-auth-operator;" in operator
    asks = conf.split("location = /fleet-auth-operator {", 1)[1].split("}", 1)[0]
    assert "proxy_pass http://127.0.0.1:9480/auth?need=operator;" in asks and "internal;" in asks
    # a page's fetch gets 401 (it cannot follow a login page), a person the login page
    login = conf.split("location @fleet_login {", 1)[1].split("\n    }", 1)[0]
    assert 'if ($http_sec_fetch_dest = "empty") { return 401; }' in login and "return 302 /login?next=" in login
    root = conf.split("    location / {", 1)[1].split("}", 1)[0]
    assert "auth_request /fleet-auth;" in root and "error_page 401 = @fleet_login;" in root
    # only the login page, the logout, nginx's own internal question, who-am-I (which reads the
    # session itself: 401 without one) and the API's health and description go without nginx asking
    unguarded = [
        b.split("{")[0] for b in conf.split("location ")[1:] if "auth_request /fleet-auth" not in b.split("}")[0]
    ]
    open_ones = ["= /favicon.ico", "= /fleet-auth", "= /fleet-auth-operator", "= /login", "= /logout", "= /session"]
    open_ones += ["= /api/docs", "= /api/health", "= /api/openapi.json", "@fleet_api_forbidden", "@fleet_api_login"]
    open_ones += ["= /tokens", "= /tokens/revoke"]
    open_ones.append("@fleet_login")
    assert sorted(u.strip() for u in unguarded) == sorted(open_ones)
    # the API: a program gets 401 (JSON), not the login page; the journal is an operator's
    api = conf.split("    location /api/ {", 1)[1].split("}", 1)[0]
    assert "error_page 401 = @fleet_api_login;" in api and "proxy_pass http://127.0.0.1:9481;" in api
    logs = conf.split("    location ~ ^/api/hosts/[^/]+/instances/[0-9]+/logs$ {", 1)[1].split("}", 1)[0]
    assert "auth_request /fleet-auth-operator;" in logs and "proxy_buffering off;" in logs
    assert "fleet_viewer" not in conf and "location = /viewers/" not in conf
    other = front_door.nginx_conf(dict(GOOD, port=8443, http_port=0, ipv6=False), "managed")
    assert "return 301" not in other and "listen 8443 ssl;" in other and "[::]" not in other


def test_files_keep_secrets_root_s_and_list_the_login_service_first():
    files = front_door.files(
        GOOD, "managed", "CERT", "KEY", {"auth": "CODE", "store": "STORE", "api": "API", "pool": "POOL"}
    )
    assert list(files) == [front_door.AUTH_UNIT, front_door.API_UNIT, front_door.UNIT]
    api = files[front_door.API_UNIT]
    assert api["/usr/local/libexec/isaac-sim/isaac-sim-front-door-api"]["content"] == "API"
    said = json.loads(api["/etc/isaac-sim/front-door/api.json"]["content"])
    assert said["hosts"] == [{"name": "gpu-1", "status_url": "http://10.0.0.5:8290/status", "agent_url": ""}], said
    assert (
        not any("/agent/" in path for path in api)
        and "--agent-tls" not in api[f"/etc/systemd/system/{front_door.API_UNIT}"]["content"]
    )
    # with the door's client certificate: its TLS files (the key root's alone) and the API told where they are
    with_agents = front_door.files(
        dict(GOOD, agent_ca="CA", agent_client_cert="CRT", agent_client_key="KEY",
             backends=[dict(GOOD["backends"][0], agent_url="https://10.0.0.5:8291")]),
        "managed", "CERT", "KEY", {"auth": "CODE", "store": "STORE", "api": "API", "pool": "POOL"},
    )[front_door.API_UNIT]  # fmt: skip
    tls = front_door.AGENT_TLS_DIR
    assert with_agents[f"{tls}/client.key"] == {"content": "KEY", "mode": "0600"}
    assert with_agents[f"{tls}/ca.crt"]["content"] == "CA" and with_agents[f"{tls}/client.crt"]["content"] == "CRT"
    assert f"--agent-tls {tls}" in with_agents[f"/etc/systemd/system/{front_door.API_UNIT}"]["content"]
    assert json.loads(with_agents["/etc/isaac-sim/front-door/api.json"]["content"])["hosts"][0]["agent_url"] == (
        "https://10.0.0.5:8291"
    )
    assert "--auth http://127.0.0.1:9480" in api["/etc/systemd/system/isaac-sim-front-door-api.service"]["content"]
    auth, door = files[front_door.AUTH_UNIT], files[front_door.UNIT]
    assert auth["/etc/isaac-sim/front-door/users.json"]["mode"] == "0600"
    assert json.loads(auth["/etc/isaac-sim/front-door/users.json"]["content"]) == {
        "olga": {"role": "operator", "hash": HASH}
    }
    assert door["/etc/isaac-sim/front-door/door.key"] == {"content": "KEY", "mode": "0600"}
    assert auth["/usr/local/libexec/isaac-sim/isaac-sim-front-door-auth"]["content"] == "CODE"
    # the store's code beside the script, which imports it under that name
    assert auth["/usr/local/libexec/isaac-sim/isaac_sim_door_store.py"]["content"] == "STORE"
    unit = auth["/etc/systemd/system/isaac-sim-front-door-auth.service"]["content"]
    assert "--port 9480 --users /etc/isaac-sim/front-door/users.json" in unit and "IPAddressAllow=localhost" in unit
    assert "--store /var/lib/isaac-sim-front-door/door.db" in unit and "StateDirectory=isaac-sim-front-door" in unit
    assert 'href="/hosts/gpu-1/status"' in door["/etc/isaac-sim/front-door/www/index.html"]["content"]


def test_each_viewer_gets_a_door_port_by_its_host_s_place_and_its_number():
    assert [(v["host"], v["instance"], v["port"]) for v in front_door.viewers(VIEWERS)] == [
        ("gpu-1", 0, 20000),
        ("gpu-2", 0, 20100),
        ("gpu-2", 3, 20103),
    ]
    assert front_door.check(VIEWERS) == []


def test_a_viewer_s_port_serves_its_page_and_its_signalling_behind_the_login():
    conf = front_door.nginx_conf(VIEWERS, "managed")
    # the entrance on the door's own port leads to the viewer's port
    assert "location = /viewers/gpu-2/3/ { return 302 https://fleet.lab:20103/; }" in conf
    server = conf.split("    listen 20103 ssl;", 1)[1].split("\n  }\n", 1)[0]
    assert "ssl_certificate /etc/isaac-sim/front-door/door.crt;" in server
    assert 'Strict-Transport-Security "max-age=31536000" always' in server
    assert 'add_header Cache-Control "no-store" always;' in server
    root = server.split("    location / {", 1)[1]
    assert "auth_request /fleet-auth-instance;" in root and "error_page 401 = @fleet_login;" in root
    # the login service is asked with the instance: one a session holds opens for its holder alone
    asks = server.split("location = /fleet-auth-instance {", 1)[1].split("}", 1)[0]
    assert "proxy_pass http://127.0.0.1:9480/auth?instance=gpu-2/3;" in asks and "internal;" in asks
    # no session: the login on the door's own port, then back here through the entrance
    assert "return 302 https://fleet.lab/login?next=/viewers/gpu-2/3/;" in server
    # a WebSocket goes to the signal port, anything else to the page, each with the Host it expects
    assert "upstream fleet_viewer_20103_page { server 10.0.0.13:8210; }" in conf
    assert "upstream fleet_viewer_20103_signal { server 10.0.0.13:49100; }" in conf
    assert (
        'map $http_upgrade $fleet_viewer_20103 { "~*^websocket$" fleet_viewer_20103_signal; '
        "default fleet_viewer_20103_page; }" in conf
    )
    assert (
        "proxy_pass http://$fleet_viewer_20103;" in root and "proxy_set_header Host $fleet_viewer_20103_host;" in root
    )
    assert "proxy_set_header Upgrade $http_upgrade;" in root and "proxy_read_timeout 1h;" in root
    # the signalling opens only from the viewer's own page, and the session stays at the door
    assert 'if ($fleet_origin ~ "^1 (?!https://fleet\\.lab:20103$)") { return 403; }' in root
    assert 'proxy_set_header Cookie "";' in root
    # the login page may lead on to the viewers' ports (Chrome holds a form's redirects to form-action)
    assert "--form-action https://fleet.lab:*" in front_door.auth_unit(VIEWERS, "managed")
    assert "--form-action" not in front_door.auth_unit(GOOD, "managed")
    page = front_door.index_page(VIEWERS)
    assert '<a href="/viewers/gpu-2/3/">viewer 3</a>' in page


RELAYED = dict(
    VIEWERS,
    turn=True,
    turn_port=5349,
    turn_min_port=50000,
    turn_max_port=50199,
    turn_gid=107,
    turn_address="10.0.0.2",
    peers=["10.0.0.5", "10.0.0.10", "10.0.0.13"],
)


@pytest.mark.parametrize(
    "over, start",
    [
        ({"turn_port": 443}, "front_door_turn_port: 443, which front_door_port already takes"),
        ({"turn_port": 0}, "front_door_turn_port: 0 is not a port"),
        ({"turn_min_port": 50200}, "front_door_turn_min_port and front_door_turn_max_port: 50200-50199 is not a range"),
        (
            {"turn_min_port": 20000, "turn_max_port": 20099},
            "front_door_turn_min_port and front_door_turn_max_port: 20000-20099 holds port 20000 of the web viewer of "
            "gpu-1 instance 0",
        ),
        ({"peers": ["gpu-1.lab"]}, "front_door_hosts: instances stream from gpu-1.lab"),
        ({"peers": ["fe80::1%eth0\nno-tlsv1_2"]}, "front_door_hosts: instances stream from fe80::1%eth0"),
        ({"turn_port": 20103}, "front_door_turn_port: 20103, which front_door_viewer_port_base gives the web viewer"),
        ({"turn_address": "10.0.0.2\nallowed-peer-ip=0.0.0.0"}, "front_door_turn: the front door host's address"),
    ],
)
def test_each_bad_relay_setting_is_named_with_its_fix(over, start):
    assert front_door.check(RELAYED) == []
    errors = front_door.check(dict(RELAYED, **over))
    assert len(errors) == 1 and errors[0].startswith(start) and "Fix:" in errors[0], errors


def test_the_relay_speaks_tls_only_relays_to_the_instances_alone_and_its_credentials_need_a_login():
    files = front_door.files(RELAYED, "managed", "CERT", "KEY", CODE, "s3cr3t")
    relay = files["isaac-sim-front-door-turn.service"]
    conf = relay["/etc/isaac-sim/front-door/turnserver.conf"]
    # the package's user reads its configuration (the secret) and the key; nobody else
    assert {k: v for k, v in conf.items() if k != "content"} == {"mode": "0640", "uid": 0, "gid": 107}
    assert relay["/etc/isaac-sim/front-door/turn.key"] == {"content": "KEY", "mode": "0640", "uid": 0, "gid": 107}
    lines = conf["content"].splitlines()
    for line in ("tls-listening-port=5349", "no-udp", "no-tcp", "no-dtls", "no-tlsv1", "no-tlsv1_1", "no-tcp-relay"):
        assert line in lines
    assert "min-port=50000" in lines and "max-port=50199" in lines and "relay-ip=10.0.0.2" in lines
    assert "use-auth-secret" in lines and "static-auth-secret=s3cr3t" in lines and "realm=fleet.lab" in lines
    # every peer denied but the instances' own addresses
    assert lines.index("denied-peer-ip=0.0.0.0-255.255.255.255") < lines.index("allowed-peer-ip=10.0.0.10")
    assert [line for line in lines if line.startswith("allowed-peer-ip=")] == [
        "allowed-peer-ip=10.0.0.10",
        "allowed-peer-ip=10.0.0.13",
        "allowed-peer-ip=10.0.0.5",
    ]
    unit = relay["/etc/systemd/system/isaac-sim-front-door-turn.service"]["content"]
    assert "ExecStart=/usr/bin/turnserver -c /etc/isaac-sim/front-door/turnserver.conf --pidfile=" in unit
    assert "User=turnserver" in unit and "User=root" not in unit and "CapabilityBoundingSet=\n" in unit
    # the login service hands out the credentials, good as long as a session
    auth = front_door.auth_unit(RELAYED, "managed")
    assert (
        "--turn-url turns:fleet.lab:5349?transport=tcp --turn-secret /etc/isaac-sim/front-door/turn.secret "
        "--turn-seconds 28800" in auth
    )
    secret = files["isaac-sim-front-door-auth.service"]["/etc/isaac-sim/front-door/turn.secret"]
    assert secret == {"content": "s3cr3t\n", "mode": "0600"}
    conf = front_door.nginx_conf(RELAYED, "managed")
    where = conf.split("location = /turn-credentials {", 1)[1].split("}", 1)[0]
    assert "proxy_pass http://127.0.0.1:9480;" in where
    assert "turn-credentials" not in front_door.nginx_conf(VIEWERS, "managed")
    # below 1024, the one capability to bind it
    low = front_door.files(dict(RELAYED, turn_port=443, port=8443), "managed", "C", "K", CODE, "s")
    assert (
        "AmbientCapabilities=CAP_NET_BIND_SERVICE"
        in low["isaac-sim-front-door-turn.service"]["/etc/systemd/system/isaac-sim-front-door-turn.service"]["content"]
    )


def test_a_viewer_s_port_follows_its_host_s_place_whatever_serves_a_status_endpoint():
    # gpu-1 serves no status endpoint: no /hosts/ path for it, its viewers still served; gpu-2 keeps
    # the ports of the third place in front_door_hosts
    p = dict(
        VIEWERS,
        server_name="Fleet.Lab",
        backends=[
            dict(VIEWERS["backends"][0], status_url="", slot=0),
            dict(VIEWERS["backends"][1], slot=2),
        ],
    )
    assert front_door.check(p) == []
    assert [v["port"] for v in front_door.viewers(p)] == [20000, 20200, 20203]
    conf = front_door.nginx_conf(p, "managed")
    assert "location = /hosts/gpu-1/status" not in conf and "location = /hosts/gpu-2/status" in conf
    assert "<li>gpu-1 <a href=" in front_door.index_page(p)
    # the Origin as browsers send it, the host in lower case
    assert 'if ($fleet_origin ~ "^1 (?!https://fleet\\.lab:20203$)") { return 403; }' in conf
    # only a WebSocket upgrade is passed on as one; the instance's page sets no cookie of the door's
    assert "map $fleet_websocket $fleet_connection { 1 upgrade; default close; }" in conf
    assert "proxy_hide_header Set-Cookie;" in conf


def test_the_door_says_its_address_certificate_relay_and_each_instance_s_entrance():
    relay = dict(RELAYED, port=8443, cert_not_after="notAfter=Nov 26 09:00:00 2027 GMT\n")
    files = front_door.files(relay, "managed", "CERT", "KEY", CODE, "SECRET")
    said = json.loads(files[front_door.UNIT]["/etc/isaac-sim/front-door/www/front-door.json"]["content"])
    assert said == {
        "url": "https://fleet.lab:8443/",
        "certificate": {"not_after": "2027-11-26T09:00:00Z"},
        "relay": {"url": "turns:fleet.lab:5349?transport=tcp", "ports": "50000-50199"},
        "entrances": {
            "gpu-1": {"0": "https://fleet.lab:8443/viewers/gpu-1/0/"},
            "gpu-2": {"0": "https://fleet.lab:8443/viewers/gpu-2/0/", "3": "https://fleet.lab:8443/viewers/gpu-2/3/"},
        },
    }
    # no relay, and an expiry openssl did not give: said so, not made up
    said = json.loads(front_door.door_json(dict(GOOD, cert_not_after="garbage")))
    assert said["relay"] is None and said["certificate"] == {"not_after": ""} and said["url"] == "https://fleet.lab/"
    six = dict(GOOD, server_name="fd00::1", turn=True, turn_port=5349, turn_min_port=1, turn_max_port=2)
    assert json.loads(front_door.door_json(six))["relay"]["url"] == "turns:[fd00::1]:5349?transport=tcp"
    # who is logged in: asked of the login service, which reads the session itself
    assert (
        "location = /session { proxy_pass http://127.0.0.1:9480; proxy_set_header X-Real-IP $remote_addr; }"
        in front_door.nginx_conf(GOOD, "managed")
    )


def test_an_instance_s_logs_go_through_the_door_to_operators_alone():
    conf = front_door.nginx_conf(dict(GOOD, backends=[dict(GOOD["backends"][0], name="gpu-1.lab")]), "managed")
    block = conf.split("    location ~ ^/operator/hosts/gpu-1[.]lab/logs/([0-9][0-9]?)$ {", 1)[1].split("}", 1)[0]
    assert "auth_request /fleet-auth-operator;" in block and "proxy_pass http://10.0.0.5:8290/logs/$1;" in block
    assert 'proxy_set_header Cookie "";' in block


def test_with_a_client_ca_every_tls_port_asks_for_a_certificate_it_signed():
    pem = "-----BEGIN CERTIFICATE-----\nMIIB\n-----END CERTIFICATE-----\n"
    asked = dict(VIEWERS, client_ca_path="/home/me/people-ca.pem", client_ca=pem)
    assert front_door.check(asked) == []
    conf = front_door.nginx_conf(asked, "managed")
    servers = conf.split("  server {")[1:]
    tls = [block for block in servers if " ssl;" in block]
    # the main port and the three viewers' ports; the plain-HTTP redirect asks nothing
    assert len(tls) == 4 and all("ssl_verify_client on;\n    ssl_verify_depth 3;" in block for block in tls)
    assert all("ssl_client_certificate /etc/isaac-sim/front-door/client-ca.crt;" in block for block in tls)
    assert "ssl_verify_client" not in servers[0]
    assert 'cert="$ssl_client_s_dn"' in conf
    files = front_door.files(asked, "managed", "CERT", "KEY", CODE)[front_door.UNIT]
    assert files["/etc/isaac-sim/front-door/client-ca.crt"] == {"content": pem, "mode": "0644"}
    # none given: none asked, no file
    plain = front_door.nginx_conf(dict(VIEWERS, client_ca_path="", client_ca=""), "managed")
    assert "ssl_verify_client" not in plain and "ssl_client_s_dn" not in plain
    assert (
        "/etc/isaac-sim/front-door/client-ca.crt" not in front_door.files(VIEWERS, "m", "C", "K", CODE)[front_door.UNIT]
    )


def test_the_api_keeps_sessions_in_the_login_service_s_store_with_the_pool_s_rules():
    p = dict(GOOD, sim={"max_minutes": "30", "per_person": 2})
    rules = json.loads(front_door.api_json(p))["pool"]
    assert rules == {
        "per_person": 2,
        "idle_minutes": 30,
        "max_minutes": 30,
        "warn_minutes": 5,
        "queue_grace_s": 120,
        "host_gone_s": 120,
        "files_mib": 1024,
        "files_dir": "/var/lib/isaac-sim-front-door/files",
        "limits": {},
    }
    assert json.loads(front_door.api_json(VIEWERS))["signals"]["gpu-2"]["3"] == "10.0.0.13:49100"
    unit = front_door.files(p, "managed", "CERT", "KEY", CODE)[front_door.API_UNIT]
    text = unit[f"/etc/systemd/system/{front_door.API_UNIT}"]["content"]
    assert f"--store {front_door.STORE}" in text and "StateDirectory=isaac-sim-front-door" in text
    assert f"PartOf={front_door.AUTH_UNIT}" in text and unit[front_door.POOL_CODE]["content"] == "POOL"


def test_the_api_writes_the_sessions_figures_where_node_exporter_reads_them():
    p = dict(GOOD, metrics_dir="/var/lib/prometheus/node-exporter")
    [api] = [s for s in front_door.services(p, "managed", "CERT", "KEY", CODE) if s["name"] == front_door.API_UNIT]
    files = {"path": "/var/lib/isaac-sim-front-door/files", "uid": 0, "gid": 0, "mode": "0700"}
    assert api["directories"] == [
        {"path": "/var/lib/prometheus/node-exporter", "uid": 0, "gid": 0, "mode": "0755"},
        files,
    ]
    text = api["files"][f"/etc/systemd/system/{front_door.API_UNIT}"]["content"]
    assert "--metrics-dir /var/lib/prometheus/node-exporter" in text
    assert "ReadWritePaths=/var/lib/prometheus/node-exporter" in text
    [bare] = [s for s in front_door.services(GOOD, "managed", "CERT", "KEY", CODE) if s["name"] == front_door.API_UNIT]
    assert (
        bare["directories"] == [files]
        and "--metrics-dir" not in bare["files"][f"/etc/systemd/system/{front_door.API_UNIT}"]["content"]
    )


def test_the_people_s_files_are_kept_where_the_api_may_write_and_nobody_else_reads():
    """In the API's state directory by default (systemd's StateDirectory: writable in its sandbox); elsewhere,
    that directory is made root's alone and opened to the sandbox too."""
    [api] = [s for s in front_door.services(GOOD, "managed", "CERT", "KEY", CODE) if s["name"] == front_door.API_UNIT]
    text = api["files"][f"/etc/systemd/system/{front_door.API_UNIT}"]["content"]
    assert "ReadWritePaths=" not in text and "StateDirectory=isaac-sim-front-door" in text
    assert json.loads(front_door.api_json(GOOD))["pool"]["files_dir"] == front_door.FILES_DIR
    p = dict(GOOD, sim={"files_dir": "/srv/door-files", "files_mib": "0"})
    assert front_door.check(p) == []
    [api] = [s for s in front_door.services(p, "managed", "CERT", "KEY", CODE) if s["name"] == front_door.API_UNIT]
    assert api["directories"] == [{"path": "/srv/door-files", "uid": 0, "gid": 0, "mode": "0700"}]
    assert "ReadWritePaths=/srv/door-files\n" in api["files"][f"/etc/systemd/system/{front_door.API_UNIT}"]["content"]
    rules = json.loads(front_door.api_json(p))["pool"]
    assert (rules["files_dir"], rules["files_mib"]) == ("/srv/door-files", 0)


def test_a_removal_takes_the_store_and_the_sessions_figures_and_leaves_each_person_s_files():
    gone = front_door.removal("/var/lib/node-exporter")
    assert front_door.STATE_DIR not in gone[front_door.AUTH_UNIT]["remove"]
    assert front_door.STORE in gone[front_door.AUTH_UNIT]["remove"]
    assert not any(path.startswith(front_door.FILES_DIR) for unit in gone.values() for path in unit["remove"])
    assert f"/var/lib/node-exporter/{pool.METRICS_FILE}" in gone[front_door.API_UNIT]["remove"]
    assert not any(path.endswith(".prom") for path in front_door.removal()[front_door.API_UNIT]["remove"])
