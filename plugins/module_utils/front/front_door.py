# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The fleet's front door (roles/front_door): one HTTPS entrance with a login in front of what the
fleet serves to browsers.

nginx of the distribution's packages runs as a unit of the collection's own
(isaac-sim-front-door.service, its own configuration, so an nginx the site runs is left alone):
TLS 1.2 and 1.3 only, HSTS, plain HTTP only as a redirect. Every request but the login page's asks
the login service (isaac-sim-front-door-auth.service, front/door_auth.py) first; login attempts
are rate-limited per client address. Behind it: each host's status endpoint, at
/hosts/HOST/status, each 6.x web viewer, and a page that lists them.

A web viewer gets a TLS port of its own on the front door (front_door_viewer_port_base + 100 x the
host's place in front_door_hosts + the instance's number): the page and, on the same port, its
signalling WebSocket, told apart by the Upgrade header. NVIDIA's viewer library takes a signalling
host, port and forceWSS (no path of its own is confirmed), so a port per viewer is what routes
its signalling to the right instance; the page, loaded over HTTPS, signals back to its own origin
over WSS (roles/web_viewer_image/files/viewer-entrypoint). /viewers/HOST/N/ redirects there.
"""

from __future__ import annotations

import datetime
import html
import json
import re

from ansible_collections.isaacsim.fleet.plugins.module_utils.common import sandbox, units
from ansible_collections.isaacsim.fleet.plugins.module_utils.common.parse import is_ip
from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_auth, turn
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

UNIT = "isaac-sim-front-door.service"
AUTH_UNIT = "isaac-sim-front-door-auth.service"
API_UNIT = "isaac-sim-front-door-api.service"
CONFIG_DIR = f"{layout.CONFIG_DIR}/front-door"
RUN_DIR = "/run/isaac-sim-front-door"
STATE_DIR = "/var/lib/isaac-sim-front-door"
AUTH_SCRIPT = f"{layout.LIBEXEC_DIR}/isaac-sim-front-door-auth"
# the store of sessions and tokens (front/door_store.py), beside the script that imports it
STORE_CODE = f"{layout.LIBEXEC_DIR}/isaac_sim_door_store.py"
STORE = f"{STATE_DIR}/door.db"
# each person's files (front/pool.py), beside the store by default
FILES_DIR = f"{STATE_DIR}/files"
API_SCRIPT = f"{layout.LIBEXEC_DIR}/isaac-sim-front-door-api"
# the simulator sessions' pool (front/pool.py), beside the API's script that imports it
POOL_CODE = f"{layout.LIBEXEC_DIR}/isaac_sim_door_pool.py"
NGINX = "/usr/sbin/nginx"
PYTHON = "/usr/bin/python3"
# nginx's workers drop to the distribution's web user (Debian's base-passwd has it)
WORKER_USER = "www-data"
_HOST_RE = re.compile(r"^[A-Za-z0-9.-]+\Z")
_RATE_RE = re.compile(r"^[1-9][0-9]*r/[sm]\Z")
_NAME_RE = re.compile(r"^[A-Za-z0-9._-]+\Z")
# ADDRESS:PORT as a host reports it; what a host's status endpoint says it serves at, and where an
# instance's web viewer and signalling listen (each goes into nginx's configuration as it is)
_ADDRESS = r"(?:[0-9.]+|\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+):[0-9]{1,5}"
_STATUS_URL_RE = re.compile(rf"^http://{_ADDRESS}/status\Z")
_AGENT_URL_RE = re.compile(rf"^https://{_ADDRESS}\Z")
# the door's client certificate for the hosts' action agents, and the CA it checks them against
AGENT_TLS_DIR = f"{CONFIG_DIR}/agent"
_PAGE_RE = re.compile(rf"^http://({_ADDRESS})/\Z")
_SIGNAL_RE = re.compile(rf"^({_ADDRESS})\Z")
# door ports per host behind it: one per instance number
VIEWER_PORTS_PER_HOST = 100
# Mozilla's "intermediate" TLS 1.2 suites: forward secrecy and AEAD only (TLS 1.3 picks its own)
CIPHERS = (
    "ECDHE-ECDSA-AES128-GCM-SHA256:ECDHE-RSA-AES128-GCM-SHA256:ECDHE-ECDSA-AES256-GCM-SHA384:"
    "ECDHE-RSA-AES256-GCM-SHA384:ECDHE-ECDSA-CHACHA20-POLY1305:ECDHE-RSA-CHACHA20-POLY1305"
)


# the pool's rules (front/pool.py RULES): the role's variable, the lowest and highest it may be, an example
_SIM = {
    "per_person": ("front_door_sim_per_person", 1, 100, 1),
    "idle_minutes": ("front_door_sim_idle_minutes", 0, 7 * 24 * 60, 30),
    "max_minutes": ("front_door_sim_max_minutes", 1, 7 * 24 * 60, 240),
    "warn_minutes": ("front_door_sim_warn_minutes", 0, 24 * 60, 5),
    "queue_grace_s": ("front_door_sim_queue_grace_seconds", 10, 24 * 3600, 120),
    "host_gone_s": ("front_door_sim_host_gone_seconds", 10, 24 * 3600, 120),
    "files_mib": ("front_door_sim_files_mib", 0, 100 * 1024, 1024),
}


def _sim_errors(sim: dict) -> list:
    errors = []
    for key, (var, low, high, example) in _SIM.items():
        value = _port(sim.get(key, example))
        if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
            errors.append(f"{var}: {value!r} is not a whole number of {low}-{high}. Fix: e.g. {example}.")
    limits = sim.get("limits") or {}
    if not isinstance(limits, dict):
        errors.append(
            f"front_door_sim_limits: {limits!r} is not a mapping. Fix: e.g. {{'role:operator': 3, 'user:olga': 2}}."
        )
        limits = {}
    for key, value in limits.items():
        value = _port(value)
        if not re.fullmatch(r"(user|role):[A-Za-z0-9._@-]{1,64}", str(key)):
            errors.append(
                f"front_door_sim_limits: {key!r} is neither user:NAME nor role:ROLE. Fix: e.g. role:operator or "
                "user:olga."
            )
        elif not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= 100:
            errors.append(f"front_door_sim_limits: {key}: {value!r} is not a whole number of 0-100. Fix: e.g. 2.")
    files_dir = _files_dir({"sim": sim})
    if not re.fullmatch(r"(/[A-Za-z0-9._-]+){2,}", files_dir) or {".", ".."} & set(files_dir.split("/")):
        errors.append(
            f"front_door_sim_files_dir: {files_dir!r} is not an absolute path of two or more parts of letters, "
            f"digits and . _ - (no . or ..). Fix: a directory of its own for the people's files, e.g. {FILES_DIR}."
        )
    elif files_dir in (STATE_DIR, CONFIG_DIR) or files_dir.startswith(CONFIG_DIR + "/"):
        errors.append(
            f"front_door_sim_files_dir: {files_dir} is the door's state or configuration directory. Fix: a "
            f"directory of its own, e.g. {FILES_DIR}."
        )
    warn = _port(sim.get("warn_minutes", 5))
    for key in ("max_minutes", "idle_minutes"):
        end = _port(sim.get(key, _SIM[key][3]))
        if isinstance(warn, int) and isinstance(end, int) and end and warn >= end:
            errors.append(
                f"front_door_sim_warn_minutes: {warn} is not below {_SIM[key][0]} ({end}). Fix: a warning that "
                "comes before the end, e.g. 5."
            )
    return errors


def sim_rules(p: dict) -> dict:
    """The pool's rules as api.json gives them to the API (checked: _sim_errors)."""
    sim = p.get("sim") or {}
    rules = {key: int(_port(sim.get(key, example))) for key, (_v, _l, _h, example) in _SIM.items()}
    rules["limits"] = {str(k): int(_port(v)) for k, v in (sim.get("limits") or {}).items()}
    rules["files_dir"] = _files_dir(p)
    return rules


def _files_dir(p: dict) -> str:
    return str((p.get("sim") or {}).get("files_dir") or FILES_DIR)


def _port(value):
    # a number given as text (ansible-core templates set_fact values to text)
    return int(value) if str(value).isdigit() else value


def check(p: dict) -> list:
    """Errors in the role's settings, each naming the variable and the fix."""
    errors = []
    name = str(p.get("server_name") or "")
    if not _HOST_RE.fullmatch(name) and not is_ip(name):
        errors.append(
            f"front_door_server_name: {name!r} is neither a host name nor an IP address. "
            "Fix: the name browsers reach the front door at, e.g. fleet.lab."
        )
    ports = {}
    for var, key, low in (
        ("front_door_port", "port", 1),
        ("front_door_http_port", "http_port", 0),
        ("front_door_auth_port", "auth_port", 1024),
        ("front_door_api_port", "api_port", 1024),
    ):
        value = _port(p.get(key))
        if not isinstance(value, int) or not low <= value <= 65535:
            errors.append(
                f"{var}: {value!r} is not a port of {low}-65535. Fix: e.g. "
                f"{ {'port': 443, 'http_port': '80 (0: no redirect)', 'auth_port': 9480, 'api_port': 9481}[key] }."
            )
        elif value:
            ports.setdefault(value, []).append(var)
    for value, names in ports.items():
        if len(names) > 1:
            errors.append(f"{' and '.join(names)}: both {value}. Fix: give each its own port.")
    if not _RATE_RE.fullmatch(str(p.get("login_rate") or "")):
        errors.append(
            f"front_door_login_rate: {p.get('login_rate')!r} is not nginx's rate. Fix: attempts per "
            "second or minute per client address, e.g. 10r/m."
        )
    hours = p.get("session_hours")
    if not isinstance(hours, (int, float)) or isinstance(hours, bool) or not 0 < hours <= 24 * 30:
        errors.append(f"front_door_session_hours: {hours!r} is not a number of hours of 0-720. Fix: e.g. 8.")
    errors += _sim_errors(p.get("sim") or {})
    metrics_dir = p.get("metrics_dir") or ""
    if metrics_dir and not re.fullmatch(r"/[A-Za-z0-9._/-]+", str(metrics_dir)):
        errors.append(
            f"front_door_metrics_textfile_dir: {metrics_dir!r} is not an absolute path of letters, digits and . _ - /. "
            "Fix: node_exporter's textfile directory, e.g. /var/lib/prometheus/node-exporter, or '' for none."
        )
    errors += _user_errors(p.get("users"))
    errors += _client_ca_errors(p)
    for backend in p.get("backends") or []:
        if not _NAME_RE.fullmatch(str(backend.get("name", ""))):
            errors.append(
                f"front_door_hosts: the inventory host {backend.get('name')!r} cannot be a path of the front "
                "door. Fix: letters, digits, '.', '_' and '-' only in the names of the hosts behind it."
            )
        elif backend.get("status_url") and not _STATUS_URL_RE.fullmatch(str(backend["status_url"])):
            errors.append(
                f"front_door_hosts: {backend['name']} says its status endpoint is at {backend.get('status_url')!r}, "
                "not http://ADDRESS:PORT/status. Fix: its isaac_sim_status_server_address, or redeploy it."
            )
        elif backend.get("agent_url") and not _AGENT_URL_RE.fullmatch(str(backend["agent_url"])):
            errors.append(
                f"front_door_hosts: {backend['name']} says its action agent is at {backend.get('agent_url')!r}, "
                "not https://ADDRESS:PORT. Fix: its isaac_sim_public_address, or redeploy it."
            )
    errors += _viewer_errors(p, ports)
    if p.get("turn"):
        errors += _turn_errors(p, ports)
    if p.get("unread"):
        errors.append(
            f"front_door_hosts: {', '.join(map(str, p['unread']))} did not say where they serve their status "
            "and viewers (unreachable, or left out by --limit), and the front door would drop them. Fix: run "
            "playbooks/front_door.yml with those hosts reachable and within --limit."
        )
    return errors


def _client_ca_errors(p: dict) -> list:
    """client_ca_path: front_door_client_ca as given; client_ca: the file's text (None: not a file)."""
    path = p.get("client_ca_path") or ""
    if not path:
        return []
    text = p.get("client_ca")
    if text is None:
        why = "is not a file on the controller"
    elif "-----BEGIN CERTIFICATE-----" not in str(text):
        why = "holds no PEM certificate"
    else:
        return []
    return [
        f"front_door_client_ca: {path!r} {why}. Fix: the path of the PEM certificate (or bundle) of the CA "
        "that signs your people's client certificates, or empty for none."
    ]


def viewers(p: dict) -> list:
    """[{host, instance, port, page, signal}]: each web viewer behind the door and its door port."""
    base = _port(p.get("viewer_port_base"))
    out = []
    for index, backend in enumerate(p.get("backends") or []):
        # its place in front_door_hosts, whichever of them serve a status endpoint
        slot = backend.get("slot", index)
        for viewer in backend.get("viewers") or []:
            port = base + VIEWER_PORTS_PER_HOST * slot + int(viewer["instance"]) if isinstance(base, int) else None
            out.append(dict(viewer, host=backend["name"], port=port))
    return out


def _viewer_errors(p: dict, ports: dict) -> list:
    base = _port(p.get("viewer_port_base"))
    if not isinstance(base, int) or not 1024 <= base <= 65535:
        return [f"front_door_viewer_port_base: {base!r} is not a port of 1024-65535. Fix: e.g. 20000."]
    errors = []
    for viewer in viewers(p):
        where = f"front_door_hosts: {viewer['host']} instance {viewer.get('instance')!r}"
        if not isinstance(viewer.get("instance"), int) or not 0 <= viewer["instance"] < VIEWER_PORTS_PER_HOST:
            errors.append(
                f"{where}: the front door serves viewers of instances 0-{VIEWER_PORTS_PER_HOST - 1}. Fix: fewer "
                "instances on that host."
            )
            continue
        if not _PAGE_RE.fullmatch(str(viewer.get("page"))) or not _SIGNAL_RE.fullmatch(str(viewer.get("signal"))):
            errors.append(
                f"{where}: its viewer at {viewer.get('page')!r} and signalling at {viewer.get('signal')!r} are not "
                "http://ADDRESS:PORT/ and ADDRESS:PORT. Fix: redeploy the host."
            )
        if viewer["port"] > 65535:
            errors.append(
                f"front_door_viewer_port_base: {base} gives {where} port {viewer['port']}, past 65535. Fix: a lower "
                "base, or fewer hosts behind this front door."
            )
        elif viewer["port"] in ports:
            errors.append(
                f"front_door_viewer_port_base: {base} gives {where} port {viewer['port']}, which "
                f"{' and '.join(ports[viewer['port']])} already takes. Fix: a base whose block of "
                f"{VIEWER_PORTS_PER_HOST} ports per host clears the front door's own ports."
            )
    return errors


def _turn_errors(p: dict, ports: dict) -> list:
    errors = []
    port, low, high = (_port(p.get(k)) for k in ("turn_port", "turn_min_port", "turn_max_port"))
    viewer_ports = {v["port"]: f"the web viewer of {v['host']} instance {v['instance']}" for v in viewers(p)}
    if not isinstance(port, int) or not 1 <= port <= 65535:
        errors.append(f"front_door_turn_port: {port!r} is not a port of 1-65535. Fix: e.g. 5349 (TURN over TLS).")
    elif port in ports:
        errors.append(f"front_door_turn_port: {port}, which {' and '.join(ports[port])} already takes. Fix: e.g. 5349.")
    elif port in viewer_ports:
        errors.append(
            f"front_door_turn_port: {port}, which front_door_viewer_port_base gives {viewer_ports[port]}. Fix: a port "
            "outside the viewers' block, e.g. 5349."
        )
    if not all(isinstance(v, int) and 1024 <= v <= 65535 for v in (low, high)) or low > high:
        return errors + [
            f"front_door_turn_min_port and front_door_turn_max_port: {low!r}-{high!r} is not a range of ports of "
            "1024-65535. Fix: e.g. 50000 and 50199 (each relayed stream takes a port of it)."
        ]
    if p.get("turn_address") and not is_ip(str(p["turn_address"])):
        errors.append(
            f"front_door_turn: the front door host's address {p['turn_address']!r} is not an IP address the relay "
            "can relay from. Fix: give the host a default IPv4 route, or front_door_turn: false."
        )
    named = [a for a in p.get("peers") or [] if not is_ip(str(a))]
    if named:
        errors.append(
            f"front_door_hosts: instances stream from {', '.join(map(str, named))}, and the relay allows peers by IP "
            "address only. Fix: give those hosts' isaac_sim_public_address as an IP address, or front_door_turn: false."
        )
    taken = dict(viewer_ports)
    taken.update({k: " and ".join(v) for k, v in ports.items()})
    if isinstance(port, int):
        taken[port] = "front_door_turn_port"
    clash = sorted(k for k in taken if low <= k <= high)
    if clash:
        errors.append(
            f"front_door_turn_min_port and front_door_turn_max_port: {low}-{high} holds port {clash[0]} of "
            f"{taken[clash[0]]}. Fix: a range of the relay's own."
        )
    return errors


def _user_errors(users) -> list:
    if not isinstance(users, list) or not users:
        return [
            "front_door_users: empty, and nobody could log in. Fix: a list of {name, role, password_hash} "
            "from a vault; make a hash with: ansible localhost -m debug -a \"msg={{ 'PASSWORD' | "
            'isaacsim.fleet.isaac_sim_password_hash }}".'
        ]
    errors, seen = [], set()
    for i, user in enumerate(users):
        if not isinstance(user, dict):
            errors.append(f"front_door_users[{i}]: not a mapping. Fix: {{name, role, password_hash}}.")
            continue
        name = user.get("name")
        where = f"front_door_users[{i}] ({name})" if isinstance(name, str) else f"front_door_users[{i}]"
        if door_auth.shown(name) != name:
            errors.append(f"{where}: the name is not 1-64 of letters, digits, '.', '_', '@' and '-'. Fix: rename it.")
        elif name in seen:
            errors.append(f"{where}: named twice. Fix: one entry per user.")
        seen.add(name)
        if user.get("role") not in door_auth.ROLES:
            errors.append(
                f"{where}: role {user.get('role')!r} is not one of {', '.join(door_auth.ROLES)}. Fix: choose one."
            )
        if "password" in user:
            errors.append(
                f"{where}: has a plain password, which would reach the host. Fix: give password_hash instead."
            )
        problem = door_auth.hash_error(user.get("password_hash"))
        if problem:
            errors.append(
                f"{where}: password_hash {problem}. Fix: make it with the isaacsim.fleet.isaac_sim_password_hash "
                "filter or Ansible's password_hash('pbkdf2_sha256')."
            )
    return errors


def nginx_conf(p: dict, managed: str) -> str:
    auth = f"http://127.0.0.1:{p['auth_port']}"
    port, http_port = int(p["port"]), int(p["http_port"])
    door = door_url(p)
    ipv6 = p.get("ipv6", True)

    def guarded(question="/fleet-auth", login="@fleet_login"):
        return [
            f"      auth_request {question};",
            "      auth_request_set $fleet_user $upstream_http_x_fleet_user;",
            "      auth_request_set $fleet_token $upstream_http_x_fleet_token;",
            f"      error_page 401 = {login};",
        ]

    def ask(location, query=""):
        return [
            f"    location = {location} {{",
            "      internal;",
            f"      proxy_pass {auth}/auth{query};",
            "      proxy_pass_request_body off;",
            '      proxy_set_header Content-Length "";',
            # as sent, for the journal; which role a path needs is this file's locations' to say
            "      proxy_set_header X-Original-URI $request_uri;",
            "      proxy_set_header X-Real-IP $remote_addr;",
            "    }",
        ]

    lines = [
        f"# {managed}",
        "# The fleet's front door (isaac-sim-front-door.service): HTTPS and a login in front of every page.",
        f"user {WORKER_USER};",
        "worker_processes 1;",
        f"pid {RUN_DIR}/nginx.pid;",
        "error_log stderr warn;",
        "events { worker_connections 512; }",
        "http {",
        "  include /etc/nginx/mime.types;",
        "  default_type application/octet-stream;",
        "  server_tokens off;",
        *(f"  {kind}_temp_path {RUN_DIR}/{kind};" for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")),
        '  log_format fleet \'$remote_addr user=$fleet_user token=$fleet_token "$request" $status'
        + (' cert="$ssl_client_s_dn"' if p.get("client_ca") else "")
        + "';",
        "  access_log syslog:server=unix:/dev/log,tag=isaac_sim_front_door,nohostname fleet;",
        # login attempts only: showing the login page costs nothing
        '  map $request_method $fleet_login_key { POST $binary_remote_addr; default ""; }',
        f"  limit_req_zone $fleet_login_key zone=fleet_login:1m rate={p['login_rate']};",
        "  limit_req_status 429;",
        "  ssl_protocols TLSv1.2 TLSv1.3;",
        f"  ssl_ciphers {CIPHERS};",
        "  ssl_session_cache shared:fleet_tls:1m;",
        "  ssl_session_tickets off;",
    ]
    if http_port:
        lines += [
            "  server {",
            f"    listen {http_port};",
            *([f"    listen [::]:{http_port};"] if ipv6 else []),
            f"    return 301 {door}$request_uri;",
            "  }",
        ]

    def tls_server(listen):
        return [
            "  server {",
            f"    listen {listen} ssl;",
            *([f"    listen [::]:{listen} ssl;"] if ipv6 else []),
            f"    ssl_certificate {CONFIG_DIR}/door.crt;",
            f"    ssl_certificate_key {CONFIG_DIR}/door.key;",
            # with a client CA, no request is read without a certificate it signed (nginx: 400)
            *(
                [
                    f"    ssl_client_certificate {CONFIG_DIR}/client-ca.crt;",
                    "    ssl_verify_client on;",
                    # a site's PKI: root, intermediates, the person's certificate
                    "    ssl_verify_depth 3;",
                ]
                if p.get("client_ca")
                else []
            ),
            '    add_header Strict-Transport-Security "max-age=31536000" always;',
            "    add_header X-Content-Type-Options nosniff always;",
            "    add_header Referrer-Policy same-origin always;",
            "    add_header X-Frame-Options DENY always;",
            # nothing behind the login stays in a browser's cache: after a logout, the page asks again
            '    add_header Cache-Control "no-store" always;',
            "    set $fleet_user -;",
            "    set $fleet_token -;",
            "    absolute_redirect off;",
            *ask("/fleet-auth"),
        ]

    def to_login(target):
        # a page's own requests (fetch: Sec-Fetch-Dest empty) and a program's (an Authorization header) get
        # 401, a person the login page
        return [
            "    location @fleet_login {",
            '      if ($http_sec_fetch_dest = "empty") { return 401; }',
            "      if ($http_authorization) { return 401; }",
            f"      return 302 {target};",
            "    }",
            "    location = /favicon.ico { access_log off; return 204; }",
        ]

    shown = viewers(p)
    if shown:
        # the signalling's WebSocket and the page share a port: the Upgrade header tells them apart
        lines += [
            '  map $http_upgrade $fleet_websocket { "~*^websocket$" 1; default 0; }',
            "  map $fleet_websocket $fleet_connection { 1 upgrade; default close; }",
        ]
    for viewer in shown:
        v = f"fleet_viewer_{viewer['port']}"
        page = _PAGE_RE.fullmatch(viewer["page"]).group(1)
        lines += [
            f"  upstream {v}_page {{ server {page}; }}",
            f"  upstream {v}_signal {{ server {viewer['signal']}; }}",
            f'  map $http_upgrade ${v} {{ "~*^websocket$" {v}_signal; default {v}_page; }}',
            # the Host each expects, as a browser reaching it directly sends it (vite checks it)
            f'  map $http_upgrade ${v}_host {{ "~*^websocket$" {viewer["signal"]}; default {page}; }}',
        ]
    lines += [
        *tls_server(port),
        *ask("/fleet-auth-operator", "?need=operator"),
        *to_login("/login?next=$request_uri"),
        "    location = /login {",
        "      limit_req zone=fleet_login burst=5 nodelay;",
        # counted by nginx, refused by the login service, which reads the user name tried and logs it
        "      limit_req_dry_run on;",
        "      proxy_set_header X-Fleet-Throttle $limit_req_status;",
        f"      proxy_pass {auth};",
        "      proxy_set_header X-Real-IP $remote_addr;",
        # the origin a browser reached the door at: the login form's POST must come from it
        "      proxy_set_header X-Fleet-Origin https://$http_host;",
        "    }",
        f"    location = /logout {{ proxy_pass {auth}; proxy_set_header X-Real-IP $remote_addr; }}",
        # who is logged in (the dashboard shows direct addresses to operators): the service reads the session
        f"    location = /session {{ proxy_pass {auth}; proxy_set_header X-Real-IP $remote_addr; }}",
        # a person's own API tokens (the console's tokens page): the login service reads the session itself
        # and refuses another site's page by the origin a browser reached the door at
        *(
            line
            for path in ("/tokens", "/tokens/revoke")
            for line in (
                f"    location = {path} {{",
                f"      proxy_pass {auth};",
                "      proxy_set_header X-Real-IP $remote_addr;",
                "      proxy_set_header X-Fleet-Origin https://$http_host;",
                "    }",
            )
        ),
        # the relay's credentials: the login service reads the session itself (401 without one)
        *(
            [
                "    location = /turn-credentials {",
                f"      proxy_pass {auth};",
                "      proxy_set_header X-Real-IP $remote_addr;",
                "    }",
            ]
            if p.get("turn")
            else []
        ),
        "    location / {",
        *guarded(),
        f"      root {CONFIG_DIR}/www;",
        "      index index.html;",
        "    }",
        # operators only (logs and actions, as they come): nginx's own match of the path decides
        "    location /operator/ {",
        *guarded("/fleet-auth-operator"),
        f"      root {CONFIG_DIR}/www;",
        "    }",
    ]
    api = f"http://127.0.0.1:{p['api_port']}"

    def streamed(path_re):
        """An operator's API path that may stream for an hour, passed on as it comes."""
        return [
            f"    location ~ {path_re} {{",
            *guarded("/fleet-auth-operator", "@fleet_api_login"),
            "      error_page 403 = @fleet_api_forbidden;",
            f"      proxy_pass {api};",
            "      proxy_set_header X-Real-IP $remote_addr;",
            "      proxy_buffering off;",
            "      proxy_read_timeout 1h;",
            "    }",
        ]

    lines += [
        # the fleet's API: a program gets 401 in JSON, never the login page; the API asks the login service
        # itself who is calling (the cookie and token go on to it, to 127.0.0.1 only)
        "    location @fleet_api_login {",
        "      default_type application/json;",
        '      return 401 \'{"error": "log in, or send an API token (Authorization: Bearer isf_...)"}\\n\';',
        "    }",
        "    location @fleet_api_forbidden {",
        "      default_type application/json;",
        '      return 403 \'{"error": "not for your role, or beyond the scopes of your token"}\\n\';',
        "    }",
        "    location /api/ {",
        *guarded(login="@fleet_api_login"),
        "      error_page 403 = @fleet_api_forbidden;",
        f"      proxy_pass {api};",
        "      proxy_set_header X-Real-IP $remote_addr;",
        # a browser's write is checked against the door's own origin, as the browser reached it
        "      proxy_set_header X-Fleet-Origin https://$http_host;",
        "      client_max_body_size 4k;",
        "    }",
        # no login: that it answers, and its own description
        *(
            f"    location = /api/{path} {{ proxy_pass {api}; proxy_set_header X-Real-IP $remote_addr; }}"
            for path in ("health", "openapi.json", "docs")
        ),
        # an instance's journal: operators (nginx's match of the path asks for the role); followed, a quiet
        # journal is no reason to end it (the API ends it when the session or token does)
        *streamed("^/api/hosts/[^/]+/instances/[0-9]+/logs$"),
        # an action's events, followed: an instance may take minutes to be ready, with no event between
        *streamed("^/api/hosts/[^/]+/actions/[a-f0-9]+$"),
    ]
    for backend in (b for b in p.get("backends") or [] if b.get("status_url")):
        base = backend["status_url"].removesuffix("/status")
        lines += [
            f"    location = /hosts/{backend['name']}/status {{",
            *guarded(),
            f"      proxy_pass {backend['status_url']};",
            # the session stays here: the hosts behind are reached over plain HTTP
            '      proxy_set_header Cookie "";',
            '      proxy_set_header Authorization "";',
            "    }",
            # an instance's journal, operators only (the host gives it to the door's address alone)
            # (names are [A-Za-z0-9._-]: only the dot means something to the regex; no braces, unquoted)
            f"    location ~ ^/operator/hosts/{backend['name'].replace('.', '[.]')}/logs/([0-9][0-9]?)$ {{",
            *guarded("/fleet-auth-operator"),
            f"      proxy_pass {base}/logs/$1;",
            '      proxy_set_header Cookie "";',
            '      proxy_set_header Authorization "";',
            "    }",
        ]
    for viewer in shown:
        # where the dashboard and the index link; the viewer's own port asks for the login
        lines.append(
            f"    location = /viewers/{viewer['host']}/{viewer['instance']}/ {{ return 302 {_entry(p, viewer)}; }}"
        )
    lines.append("  }")
    for viewer in shown:
        v = f"fleet_viewer_{viewer['port']}"
        # browsers send the host in lower case
        origin = _entry(p, viewer).rstrip("/").lower()
        lines += [
            *tls_server(viewer["port"]),
            # an instance a session holds opens for its holder (and operators) alone: the login service reads
            # the sessions' store
            *ask("/fleet-auth-instance", f"?instance={viewer['host']}/{viewer['instance']}"),
            *to_login(f"{door}/login?next=/viewers/{viewer['host']}/{viewer['instance']}/"),
            "    location / {",
            *guarded("/fleet-auth-instance"),
            # another site's page never opens this signalling with the person's session
            '      set $fleet_origin "$fleet_websocket $http_origin";',
            f'      if ($fleet_origin ~ "^1 (?!{re.escape(origin)}$)") {{ return 403; }}',
            f"      proxy_pass http://${v};",
            "      proxy_http_version 1.1;",
            f"      proxy_set_header Host ${v}_host;",
            "      proxy_set_header Upgrade $http_upgrade;",
            # a cookie of the instance's page would hold for every port of the front door's name
            "      proxy_hide_header Set-Cookie;",
            "      proxy_set_header Connection $fleet_connection;",
            '      proxy_set_header Cookie "";',
            '      proxy_set_header Authorization "";',
            # the signalling is quiet once the stream runs; nginx's 60 s would end the session
            "      proxy_read_timeout 1h;",
            "      proxy_send_timeout 1h;",
            "    }",
            "  }",
        ]
    lines.append("}")
    return "\n".join(lines) + "\n"


def door_url(p: dict) -> str:
    """The front door's own address, without a trailing slash."""
    port = int(p["port"])
    return f"https://{_bracketed(p['server_name'])}" + ("" if port == 443 else f":{port}")


def relay_url(p: dict) -> str:
    """The TURN relay as the login service hands it out and front-door.json names it."""
    return turn.url(_bracketed(p["server_name"]), p["turn_port"])


def not_after(openssl_enddate: str) -> str:
    """openssl x509 -enddate's "notAfter=Nov 26 09:00:00 2027 GMT" as ISO 8601 UTC; "" if it is not that."""
    text = openssl_enddate.strip().removeprefix("notAfter=")
    try:
        when = datetime.datetime.strptime(text, "%b %d %H:%M:%S %Y GMT")
    except ValueError:
        return ""
    return when.strftime("%Y-%m-%dT%H:%M:%SZ")


def door_json(p: dict) -> str:
    """What the front door says of itself (no secret), served to logged-in users at /front-door.json
    and read by playbooks/status.yml: its address, its certificate's expiry, its relay, and each
    instance's entrance (the address a person opens: through the login to the instance's viewer)."""
    door = door_url(p)
    entrances: dict = {}
    for viewer in viewers(p):
        entrances.setdefault(viewer["host"], {})[str(viewer["instance"])] = (
            f"{door}/viewers/{viewer['host']}/{viewer['instance']}/"
        )
    relay = (
        {
            "url": relay_url(p),
            "ports": f"{p['turn_min_port']}-{p['turn_max_port']}",
        }
        if p.get("turn")
        else None
    )
    body = {
        "url": door + "/",
        "certificate": {"not_after": not_after(str(p.get("cert_not_after") or ""))},
        "relay": relay,
        "entrances": entrances,
    }
    return json.dumps(body, indent=2, sort_keys=True) + "\n"


def _bracketed(name) -> str:
    return f"[{name}]" if ":" in str(name) else str(name)


def _entry(p: dict, viewer: dict) -> str:
    return f"https://{_bracketed(p['server_name'])}:{viewer['port']}/"


# A person's own API tokens, behind the login: made (shown once), listed and revoked through the
# login service's /tokens; a viewer is offered the read scope alone.
# a person's simulator: ask, wait in the queue, open it, see the time left and the warning, end it
# (the page's own requests keep a place in the queue while it is open)
SIM_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Isaac Sim fleet: your simulator</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>body{font-family:system-ui,sans-serif;max-width:48em;margin:2em auto}.error{color:#b00020}
#warning{background:#fff3cd;border:1px solid #c9a227;padding:.6em}#state{font-size:1.2em}</style></head>
<body><h1>Your simulator</h1>
<p id="state">Reading your sessions\u2026</p>
<p id="warning" hidden></p>
<p id="files" hidden></p>
<p id="entrance" hidden><a id="open" target="_blank" rel="noopener">Open your simulator's viewer</a></p>
<p id="left" hidden></p>
<p id="choose" hidden></p>
<p><button type="button" id="ask" hidden>Ask for a simulator</button>
<button type="button" id="end" hidden>End my session</button></p>
<p id="said" class="error" hidden></p>
<p><a href="/">The front door</a> \u00b7 <a href="/logout">Log out</a></p>
<script>
(function () {
  "use strict";
  var csrf = "", current = null, last = null, left = null;
  var $ = function (id) { return document.getElementById(id); };
  // what a request may name ([field, the fleet listing's key, label]): offered where the fleet has several
  var WANTS = [["release", "release", "Release"], ["profile", "profile", "Profile"], ["gpu", "gpu_model", "GPU"]];
  function offer(fleet) {
    WANTS.forEach(function (w) {
      var seen = {};
      (fleet.hosts || []).forEach(function (h) {
        (h.instances || []).forEach(function (i) { if (i[w[1]]) { seen[i[w[1]]] = true; } });
      });
      var values = Object.keys(seen).sort();
      if (values.length < 2) { return; }
      var label = document.createElement("label"), select = document.createElement("select");
      select.id = "want-" + w[0];
      [""].concat(values).forEach(function (v) {
        var o = document.createElement("option");
        o.value = v;
        o.textContent = v || "any";
        select.appendChild(o);
      });
      label.appendChild(document.createTextNode(w[2] + " "));
      label.appendChild(select);
      $("choose").appendChild(label);
      $("choose").appendChild(document.createTextNode(" "));
    });
  }
  function show(id, text) { $(id).textContent = text || ""; $(id).hidden = !text; }
  function call(method, path, body) {
    var headers = {"Content-Type": "application/json", "X-Fleet-CSRF": csrf};
    var asked = {method: method, cache: "no-store", headers: headers};
    if (body !== undefined) { asked.body = JSON.stringify(body); }
    return fetch(path, asked).then(function (r) {
      return r.json().catch(function () { return {}; }).then(function (a) { return [r.status, a]; });
    });
  }
  function clock(s) {
    var h = Math.floor(s / 3600), m = Math.floor(s % 3600 / 60), x = Math.floor(s % 60);
    return h + ":" + (m < 10 ? "0" : "") + m + ":" + (x < 10 ? "0" : "") + x;
  }
  function render(s) {
    current = s && (s.state === "active" || s.state === "queued" || s.state === "ending") ? s : null;
    if (s) { last = s.id; }
    document.body.dataset.state = s ? s.state : "none";
    $("ask").hidden = !!current;
    $("choose").hidden = !!current || !$("choose").childNodes.length;
    $("end").hidden = !current || current.state === "ending";
    $("end").textContent = current && current.state === "queued" ? "Leave the queue" : "End my session";
    $("entrance").hidden = !(s && s.state === "active" && s.entrance);
    if (s && s.entrance) { $("open").href = s.entrance; }
    show("warning", s && s.state === "active" ? s.warning : "");
    // what became of the person's files (Documents): put back, kept for the next session, or why not
    show("files", s && s.state !== "queued" ? s.files : "");
    left = s && s.state === "active" ? s.seconds_left : null;
    show("left", left === null ? "" : "Time left: " + clock(left));
    if (!s) { show("state", "You hold no simulator."); return; }
    if (s.state === "queued") {
      show("state", "You are number " + s.place + " of " + s.waiting + " in the queue" +
        (s.estimate_s ? " (at most about " + Math.ceil(s.estimate_s / 60) + " minutes)" : "") +
        ". Keep this page open: your place is kept while it is.");
    } else if (s.state === "active") {
      show("state", "Your simulator: " + s.host + ", instance " + s.instance + ".");
    } else if (s.state === "ending") {
      show("state", "Your session ended (" + s.why + "); its simulator is being reset.");
    } else {
      show("state", "Your session ended (" + s.why + ").");
    }
  }
  function poll() {
    call("GET", "/api/sessions").then(function (res) {
      if (res[0] !== 200) { show("said", res[1].error || "HTTP " + res[0]); return; }
      var mine = res[1].mine || [];
      if (mine.length || !last) { render(mine[0] || null); return; }
      return call("GET", "/api/sessions/" + last).then(function (one) { render(one[0] === 200 ? one[1] : null); });
    }).catch(function (e) { show("said", "The fleet could not be asked: " + e.message); })
      .then(function () { document.body.dataset.ready = "yes"; });
  }
  $("ask").addEventListener("click", function () {
    show("said", "");
    var body = {};
    WANTS.forEach(function (w) { var s = $("want-" + w[0]); if (s && s.value) { body[w[0]] = s.value; } });
    call("POST", "/api/sessions", body).then(function (res) {
      if (res[0] === 201 || res[0] === 202) { render(res[1]); } else { show("said", res[1].error || "HTTP " + res[0]); }
    });
  });
  $("end").addEventListener("click", function () {
    if (!current) { return; }
    call("DELETE", "/api/sessions/" + current.id).then(function (res) {
      if (res[0] === 200) { render(res[1]); } else { show("said", res[1].error || "HTTP " + res[0]); }
    });
  });
  setInterval(function () {
    if (left !== null && left > 0) { left -= 1; show("left", "Time left: " + clock(left)); }
  }, 1000);
  fetch("/session", {cache: "no-store"}).then(function (r) { return r.json(); }).then(function (who) {
    csrf = who.csrf || "";
    // the choices first (a page without them still asks for any), then the person's sessions
    return fetch("/api/fleet", {cache: "no-store"}).then(function (r) { return r.ok ? r.json() : {}; })
      .then(offer, function () {}).then(function () {
        poll();
        setInterval(poll, 2000);
      });
  }).catch(function (e) { show("said", "Who you are could not be read: " + e.message); });
})();
</script></body></html>
"""

TOKENS_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Isaac Sim fleet: your API tokens</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>body{font-family:system-ui,sans-serif;max-width:48em;margin:2em auto}td,th{padding:.2em .6em;text-align:left}
#made{background:#f6f8fa;padding:.6em;word-break:break-all}.error{color:#b00020}</style></head>
<body><h1>Your API tokens</h1>
<p>A token lets a program act as you, within its scopes: send it as
<code>Authorization: Bearer TOKEN</code>. It is shown once, when made.</p>
<form id="make"><label>Name <input name="name" required pattern="[A-Za-z0-9._@\\-]{1,64}"></label>
<fieldset id="scopes"><legend>Scopes</legend></fieldset>
<label>Days <input name="days" type="number" min="1" max="365" value="30" required></label>
<button type="submit">Make a token</button></form>
<p id="said" class="error" hidden></p><p id="made" hidden></p>
<table><thead><tr><th>Name</th><th>Scopes</th><th>State</th><th>Until</th><th></th></tr></thead>
<tbody id="tokens"></tbody></table>
<p><a href="/">The front door</a> \u00b7 <a href="/logout">Log out</a></p>
<script>
(function () {
  "use strict";
  var said = document.getElementById("said"), made = document.getElementById("made");
  function show(text) { said.textContent = text; said.hidden = !text; }
  function send(path, body) {
    var asked = {method: "POST", headers: {"Content-Type": "application/json"}, body: JSON.stringify(body)};
    return fetch(path, asked).then(function (r) {
      return r.json().catch(function () { return {}; }).then(function (a) { return [r.status, a]; });
    });
  }
  function list() {
    return fetch("/tokens", {cache: "no-store"}).then(function (r) {
      if (!r.ok) { throw new Error("HTTP " + r.status); }
      return r.json();
    }).then(function (mine) {
      var box = document.getElementById("scopes");
      if (box.querySelectorAll("input").length === 0) {
        mine.scopes.forEach(function (s) {
          var label = document.createElement("label"), input = document.createElement("input");
          input.type = "checkbox"; input.name = "scope"; input.value = s; input.checked = s === "read";
          label.appendChild(input); label.appendChild(document.createTextNode(" " + s + " "));
          box.appendChild(label);
        });
      }
      var body = document.getElementById("tokens");
      body.textContent = "";
      mine.tokens.forEach(function (t) {
        var tr = document.createElement("tr");
        tr.dataset.name = t.name;
        [t.name, t.scopes.join(", "), t.state, new Date(t.expires * 1000).toISOString().slice(0, 16).replace("T", " ")]
          .forEach(function (v) { var td = document.createElement("td"); td.textContent = v; tr.appendChild(td); });
        var td = document.createElement("td");
        if (t.state === "active") {
          var b = document.createElement("button");
          b.type = "button"; b.className = "revoke"; b.textContent = "revoke";
          b.addEventListener("click", function () {
            send("/tokens/revoke", {name: t.name}).then(function (res) {
              show(res[0] === 200 ? "" : res[1].error);
              list();
            });
          });
          td.appendChild(b);
        }
        tr.appendChild(td);
        body.appendChild(tr);
      });
      document.body.dataset.ready = "yes";
    }).catch(function (e) { show("Your tokens could not be read: " + e.message); });
  }
  document.getElementById("make").addEventListener("submit", function (ev) {
    ev.preventDefault();
    var form = ev.target;
    var checked = form.querySelectorAll("input[name=scope]:checked");
    var scopes = Array.prototype.map.call(checked, function (i) { return i.value; });
    // (form.name is the form's own name, not its input's)
    var name = form.querySelector("input[name=name]").value;
    var days = Number(form.querySelector("input[name=days]").value);
    send("/tokens", {name: name, scopes: scopes, days: days}).then(function (res) {
      if (res[0] === 201) {
        show("");
        made.textContent = res[1].token;
        made.hidden = false;
      } else {
        show((res[1].errors || [res[1].error || "HTTP " + res[0]]).join(" "));
      }
      list();
    });
  });
  list();
})();
</script></body></html>
"""


def index_page(p: dict) -> str:
    shown = viewers(p)
    rows = "".join(
        (
            f'<li><a href="/hosts/{html.escape(b["name"])}/status">{html.escape(b["name"])}</a>'
            if b.get("status_url")
            else f"<li>{html.escape(b['name'])}"
        )
        + "".join(
            f' <a href="/viewers/{html.escape(v["host"])}/{v["instance"]}/">viewer {v["instance"]}</a>'
            for v in shown
            if v["host"] == b["name"]
        )
        + "</li>"
        for b in p.get("backends") or []
    )
    return (
        '<!doctype html>\n<html lang="en"><head><meta charset="utf-8"><title>Isaac Sim fleet</title></head>\n'
        "<body><h1>Isaac Sim fleet</h1>"
        '<p><a href="/dashboard.html">The dashboard</a> (written here by playbooks/status.yml)</p>'
        f"<p>Each host's status:</p><ul>{rows}</ul>"
        '<p><a href="/simulator.html">A simulator for you</a> \u00b7 <a href="/tokens.html">Your API tokens</a> '
        '\u00b7 <a href="/api/docs">the fleet\'s API</a></p>'
        '<p><a href="/logout">Log out</a></p></body></html>\n'
    )


def users_json(p: dict) -> str:
    return json.dumps({u["name"]: {"role": u["role"], "hash": u["password_hash"]} for u in p["users"]}, indent=2) + "\n"


def nginx_unit(managed: str) -> str:
    return units.render(
        [
            (
                "Unit",
                [
                    ("Description", "isaacsim.fleet front door (HTTPS and login)"),
                    ("Wants", f"network-online.target {AUTH_UNIT}"),
                    ("After", f"network-online.target {AUTH_UNIT}"),
                ],
            ),
            (
                "Service",
                [
                    ("ExecStartPre", f"{NGINX} -t -q -c {CONFIG_DIR}/nginx.conf"),
                    ("ExecStart", f"{NGINX} -c {CONFIG_DIR}/nginx.conf -g 'daemon off;'"),
                    ("Restart", "on-failure"),
                    ("RestartSec", 5),
                    ("RuntimeDirectory", RUN_DIR.rsplit("/", 1)[1]),
                    *sandbox.web_server(),
                ],
            ),
            ("Install", [("WantedBy", "multi-user.target")]),
        ],
        header=[managed],
    )


def auth_unit(p: dict, managed: str) -> str:
    state = STATE_DIR.rsplit("/", 1)[1]
    return units.render(
        [
            (
                "Unit",
                [("Description", "isaacsim.fleet front door login service"), ("After", "network.target")],
            ),
            (
                "Service",
                [
                    (
                        "ExecStart",
                        f"{PYTHON} {AUTH_SCRIPT} --port {p['auth_port']} --users {CONFIG_DIR}/users.json "
                        f"--store {STORE} --hours {p['session_hours']}"
                        # after a login, the web viewers' ports of this front door
                        + (f" --form-action https://{_bracketed(p['server_name'])}:*" if viewers(p) else "")
                        # the relay's credentials live as long as a session
                        + (
                            f" --turn-url {relay_url(p)}"
                            f" --turn-secret {CONFIG_DIR}/turn.secret"
                            f" --turn-seconds {int(float(p['session_hours']) * 3600)}"
                            if p.get("turn")
                            else ""
                        ),
                    ),
                    ("Restart", "on-failure"),
                    ("RestartSec", 2),
                    ("StateDirectory", state),
                    *sandbox.reader(),
                    # no GPU to ask, unlike the other readers
                    ("PrivateDevices", "yes"),
                    ("ProtectProc", "invisible"),
                    ("IPAddressAllow", "localhost"),
                    ("IPAddressDeny", "any"),
                ],
            ),
            ("Install", [("WantedBy", "multi-user.target")]),
        ],
        header=[managed],
    )


def api_unit(p: dict, managed: str) -> str:
    return units.render(
        [
            (
                "Unit",
                [
                    ("Description", "isaacsim.fleet front door: the fleet's API"),
                    ("Wants", f"network-online.target {AUTH_UNIT}"),
                    ("After", f"network-online.target {AUTH_UNIT}"),
                    # it runs the login service's store code (the sessions' file): a new one restarts both
                    ("PartOf", AUTH_UNIT),
                ],
            ),
            (
                "Service",
                [
                    (
                        "ExecStart",
                        f"{PYTHON} {API_SCRIPT} --port {p['api_port']} --config {CONFIG_DIR}/api.json "
                        f"--auth http://127.0.0.1:{p['auth_port']} --store {STORE}"
                        + (f" --agent-tls {AGENT_TLS_DIR}" if p.get("agent_client_cert") else "")
                        + (f" --metrics-dir {p['metrics_dir']}" if p.get("metrics_dir") else ""),
                    ),
                    ("Restart", "on-failure"),
                    ("RestartSec", 2),
                    # it reads the hosts' status endpoints on the LAN, and asks the login service on 127.0.0.1;
                    # it writes the simulator sessions and their queue beside the login service's (SQLite)
                    ("StateDirectory", STATE_DIR.rsplit("/", 1)[1]),
                    # and the sessions' figures for node_exporter's textfile collector, and the people's files
                    # (where they are not in its state directory)
                    *sandbox.reader(
                        writable=([p["metrics_dir"]] if p.get("metrics_dir") else [])
                        + ([] if _files_dir(p).startswith(STATE_DIR + "/") else [_files_dir(p)])
                    ),
                    ("PrivateDevices", "yes"),
                    ("ProtectProc", "invisible"),
                ],
            ),
            ("Install", [("WantedBy", "multi-user.target")]),
        ],
        header=[managed],
    )


def _signals(p: dict) -> dict:
    out = {}
    for viewer in viewers(p):
        out.setdefault(viewer["host"], {})[str(viewer["instance"])] = viewer["signal"]
    return out


def api_json(p: dict) -> str:
    """What the API serves of the door (no secret): the hosts behind it and where their status is,
    the entrances, the relay, the session length."""
    door = json.loads(door_json(p))
    body = {
        "door": door["url"],
        "relay": door["relay"],
        "entrances": door["entrances"],
        "session_hours": p["session_hours"],
        "pool": sim_rules(p),
        # where each web viewer's signalling is relayed to: a session's stream with nobody on it ends (idle)
        "signals": _signals(p),
        "hosts": [
            {"name": b["name"], "status_url": b["status_url"], "agent_url": b.get("agent_url") or ""}
            for b in p.get("backends") or []
            if b.get("status_url")
        ],
    }
    return json.dumps(body, indent=2, sort_keys=True) + "\n"


def files(p: dict, managed: str, cert: str, key: str, code: dict, secret: str = "") -> dict:
    """{unit: {path: {content, mode}}} for isaac_sim_host_service, the login service's first (nginx
    asks it from its first request on); the TURN relay's where p["turn"] (secret: its shared
    secret; p["turn_gid"]: the group of the package's user, which reads its files)."""
    out = {
        AUTH_UNIT: {
            f"/etc/systemd/system/{AUTH_UNIT}": {"content": auth_unit(p, managed), "mode": "0644"},
            AUTH_SCRIPT: {"content": code["auth"], "mode": "0644"},
            STORE_CODE: {"content": code["store"], "mode": "0644"},
            f"{CONFIG_DIR}/users.json": {"content": users_json(p), "mode": "0600"},
            **({f"{CONFIG_DIR}/turn.secret": {"content": secret + "\n", "mode": "0600"}} if p.get("turn") else {}),
        },
        API_UNIT: {
            f"/etc/systemd/system/{API_UNIT}": {"content": api_unit(p, managed), "mode": "0644"},
            API_SCRIPT: {"content": code["api"], "mode": "0644"},
            POOL_CODE: {"content": code["pool"], "mode": "0644"},
            f"{CONFIG_DIR}/api.json": {"content": api_json(p), "mode": "0644"},
            **(
                {
                    f"{AGENT_TLS_DIR}/ca.crt": {"content": p["agent_ca"], "mode": "0644"},
                    f"{AGENT_TLS_DIR}/client.crt": {"content": p["agent_client_cert"], "mode": "0644"},
                    f"{AGENT_TLS_DIR}/client.key": {"content": p["agent_client_key"], "mode": "0600"},
                }
                if p.get("agent_client_cert")
                else {}
            ),
        },
        UNIT: {
            f"/etc/systemd/system/{UNIT}": {"content": nginx_unit(managed), "mode": "0644"},
            f"{CONFIG_DIR}/nginx.conf": {"content": nginx_conf(p, managed), "mode": "0644"},
            f"{CONFIG_DIR}/door.crt": {"content": cert, "mode": "0644"},
            f"{CONFIG_DIR}/door.key": {"content": key, "mode": "0600"},
            f"{CONFIG_DIR}/www/index.html": {"content": index_page(p), "mode": "0644"},
            f"{CONFIG_DIR}/www/tokens.html": {"content": TOKENS_PAGE, "mode": "0644"},
            f"{CONFIG_DIR}/www/simulator.html": {"content": SIM_PAGE, "mode": "0644"},
            f"{CONFIG_DIR}/www/front-door.json": {"content": door_json(p), "mode": "0644"},
            **(
                {f"{CONFIG_DIR}/client-ca.crt": {"content": p["client_ca"], "mode": "0644"}}
                if p.get("client_ca")
                else {}
            ),
        },
    }
    if p.get("turn"):
        group = {"mode": "0640", "uid": 0, "gid": int(p["turn_gid"])}
        out[turn.UNIT] = {
            f"/etc/systemd/system/{turn.UNIT}": {
                "content": turn.unit(CONFIG_DIR, managed, int(p["turn_port"]) < 1024),
                "mode": "0644",
            },
            f"{CONFIG_DIR}/turnserver.conf": dict(group, content=turn.conf(p, CONFIG_DIR, secret, CIPHERS, managed)),
            f"{CONFIG_DIR}/turn.crt": dict(group, content=cert),
            f"{CONFIG_DIR}/turn.key": dict(group, content=key),
        }
    return out


def services(p: dict, managed: str, cert: str, key: str, code: dict, secret: str = "") -> list:
    """[{name, state, files, directories, remove}] for isaac_sim_host_service, in order: what runs,
    started; the relay, when off, stopped and removed with its files."""
    present, gone = files(p, managed, cert, key, code, secret), removal(p.get("metrics_dir") or "")
    made = {
        API_UNIT: ([{"path": p["metrics_dir"], "uid": 0, "gid": 0, "mode": "0755"}] if p.get("metrics_dir") else [])
        # the people's files: root's alone
        + [{"path": _files_dir(p), "uid": 0, "gid": 0, "mode": "0700"}]
    }
    return [
        {"name": u, "state": "started", "files": present[u], "directories": made.get(u, []), "remove": []}
        if u in present
        else {"name": u, "state": "absent", "files": gone[u]["files"], "remove": gone[u]["remove"]}
        for u in gone
    ]


# the sessions' figures the API writes in node_exporter's textfile directory (pool.METRICS_FILE)
SESSIONS_METRICS = "isaac_sim_sessions.prom"


def end_sessions(wait_s: int) -> dict:
    """What the removal runs before anything goes: the API's own code, serving nothing, ends every session
    and place as any end is (each claim given back on its host, each person's files kept), waiting up to
    wait_s for the hosts; its last line says what it did (fleet_api.main --end-sessions)."""
    return {
        "unit": API_UNIT,
        "store": STORE,
        "argv": [PYTHON, API_SCRIPT, "--config", f"{CONFIG_DIR}/api.json", "--store", STORE,
                 "--agent-tls", AGENT_TLS_DIR, "--end-sessions", "the front door was removed", "--wait", str(wait_s)],
    }  # fmt: skip


def removal(metrics_dir: str = "") -> dict:
    """{unit: {files, remove}} for isaac_sim_host_service's state absent: each unit's own file, and
    what it leaves (the configuration with the dashboard status.yml wrote, the script, the session
    key, the store); in the order files() gives them. Each person's files stay."""
    return {
        AUTH_UNIT: {
            "files": {f"/etc/systemd/system/{AUTH_UNIT}": {"content": ""}},
            # the store (SQLite: its write-ahead log and index beside it), never the people's files (FILES_DIR):
            # a removal of the door is no reason to lose what people saved; they stay for an operator
            "remove": [AUTH_SCRIPT, STORE_CODE, *(f"{STORE}{end}" for end in ("", "-wal", "-shm", "-journal"))],
        },
        API_UNIT: {
            "files": {f"/etc/systemd/system/{API_UNIT}": {"content": ""}},
            # and its figures, which node_exporter would otherwise go on reading as if the door still ran
            "remove": [API_SCRIPT, POOL_CODE] + ([f"{metrics_dir}/{SESSIONS_METRICS}"] if metrics_dir else []),
        },
        UNIT: {"files": {f"/etc/systemd/system/{UNIT}": {"content": ""}}, "remove": [CONFIG_DIR]},
        turn.UNIT: {
            "files": {f"/etc/systemd/system/{turn.UNIT}": {"content": ""}},
            "remove": [f"{CONFIG_DIR}/{name}" for name in ("turnserver.conf", "turn.crt", "turn.key", "turn.secret")]
            + [f"/var/lib/{turn.STATE}"],
        },
    }
