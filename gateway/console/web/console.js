// Shared by every page: the session (user, role, CSRF token), JSON requests, WebSockets that
// reconnect, the header with its e-stop button, the safety panel, units, and messages.
const ROLES = ['none', 'read', 'operate', 'engineer'];

export function allows(role, need) { return ROLES.indexOf(role) >= ROLES.indexOf(need); }

export async function session() {
  const response = await fetch('/api/session', { credentials: 'same-origin' });
  if (response.status === 401) {
    // The page to come back to, as a path of this console (login.js follows nothing else).
    location.href = '/login?next=' + encodeURIComponent(location.pathname + location.search);
    throw new Error('log in first');
  }
  return response.json();
}

let csrf = '';

export async function api(method, url, body) {
  const options = { method, credentials: 'same-origin', headers: {} };
  if (method !== 'GET') {
    options.headers['Content-Type'] = 'application/json';
    options.headers['X-CSRF-Token'] = csrf;
    options.body = JSON.stringify(body || {});
  }
  let response;
  try {
    response = await fetch(url, options);
  } catch (e) {
    // No HTTP answer at all: the connection closed before one (the gateway stopped, the network
    // went, or the console's door made room for other connections while this one waited).
    throw new Error(`no answer from the gateway to ${method} ${url} (the connection closed before one came: ` +
      'is the gateway running and reachable? under many connections at once, try again; reload the page to see ' +
      'what was carried out)');
  }
  let data = {};
  try { data = await response.json(); } catch (e) { data = { error: response.statusText }; }
  if (!response.ok) throw new Error(data.error || ('HTTP ' + response.status));
  return data;
}

export function say(text, kind) {
  const element = document.getElementById('message');
  if (!element) return;
  element.textContent = text;
  element.className = kind || '';
}

// A WebSocket on `path` that reconnects; `onMessage` gets each parsed message, `onOpen` (if given)
// runs at each (re)connection, e.g. to send the page's settings again.
export function live(path, onMessage, onOpen) {
  const state = { socket: null, closed: false };
  const scheme = location.protocol === 'https:' ? 'wss://' : 'ws://';
  const open = () => {
    const socket = new WebSocket(scheme + location.host + path + '?csrf=' + encodeURIComponent(csrf));
    state.socket = socket;
    socket.onmessage = (event) => onMessage(JSON.parse(event.data));
    socket.onopen = () => {
      setLink(true);
      if (onOpen) onOpen();
    };
    socket.onclose = () => {
      setLink(false);
      if (!state.closed) setTimeout(open, 1000);
    };
  };
  open();
  state.send = (message) => {
    if (state.socket && state.socket.readyState === WebSocket.OPEN) state.socket.send(JSON.stringify(message));
  };
  return state;
}

function setLink(up) {
  const element = document.getElementById('link-state');
  if (element) element.textContent = up ? 'live' : 'reconnecting…';
}

export function element(tag, attributes, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attributes || {})) {
    if (key === 'class') node.className = value;
    else if (key.startsWith('on')) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, value);
  }
  for (const child of children) node.append(child instanceof Node ? child : String(child));
  return node;
}

let estopLatched = false;

// The header of every page: navigation, who is logged in, and the e-stop button (operate).
export async function header(active) {
  const me = await session();
  csrf = me.csrf;
  const bar = document.querySelector('header');
  const nav = element('nav', {}, element('a', { href: '/', class: active === 'overview' ? 'active' : '' }, 'Overview'),
    element('a', { href: '/commission', class: active === 'commission' ? 'active' : '' }, 'Commissioning'));
  const estop = element('button', { id: 'estop', title: 'Stops every servo on every bus and refuses motion until reset' }, 'E-STOP');
  estop.disabled = !allows(me.role, 'operate');
  if (estop.disabled) estop.title = 'needs the operate role';
  estop.addEventListener('click', async () => {
    try {
      if (!estopLatched) {
        await api('POST', '/api/estop', { latch: true });
        say('e-stop latched: every servo stopped, motion refused until reset', 'error');
        setEstop(true);
      } else if (confirm('Reset the e-stop? Motion writes are accepted again (nothing moves by itself).')) {
        await api('POST', '/api/estop', { latch: false });
        say('e-stop reset', 'done');
        setEstop(false);
      }
    } catch (error) { say(error.message, 'error'); }
  });
  const who = element('span', { class: 'who' }, `${me.user} (${me.role})`);
  const parts = [element('span', { class: 'brand' }, 'sms-gateway'), nav, element('span', { class: 'spacer' }),
    element('span', { id: 'link-state' }, ''), who];
  if (me.logout) {
    parts.push(element('button', { class: 'link', onclick: async () => {
      await api('POST', '/api/logout'); location.href = '/login';
    } }, 'log out'));
  }
  parts.push(estop);
  bar.replaceChildren(...parts);
  startSafetyPanel(me);
  return me;
}

export function setEstop(latched) {
  estopLatched = latched;
  const button = document.getElementById('estop');
  if (!button) return;
  button.classList.toggle('latched', latched);
  button.textContent = latched ? 'E-STOP LATCHED — reset…' : 'E-STOP';
}

// --- units ------------------------------------------------------------------------------------------
// `scale` is what the gateway read from the table's unit (console_view.cpp unit_scale): the value
// in the cell's unit is raw × scale. null: no plain scale, the raw value is shown as it is.
export function scaled(raw, scale) {
  if (raw === null || raw === undefined || raw === '') return raw;
  if (!scale) return raw;
  return Number((raw * scale.scale).toFixed(scale.decimals));
}

export function withUnit(raw, scale) {
  if (raw === null || raw === undefined || raw === '') return '';
  if (!scale) return String(raw);
  return scaled(raw, scale).toFixed(scale.decimals) + (scale.symbol.startsWith('°') && scale.symbol.length === 1 ? '' : ' ') + scale.symbol;
}

// --- the safety panel of every page -------------------------------------------------------------------
// Per bus: its watchdog (state, timeout, what feeds it, time since the last feed, trips and the last
// stop's cause), owed stops and whether motion is refused and why; the e-stop latch; re-arm and
// reset for the operate role. Fed by the overview's WebSocket, which every page opens once here.
const overviewListeners = [];
let lastOverview = null;
export function onOverview(listener) {
  overviewListeners.push(listener);
  if (lastOverview) listener(lastOverview);
}

function clock(msAgo) {
  const when = new Date(Date.now() - msAgo);
  return when.toLocaleTimeString('en-GB', { hour12: false });
}

function seconds(ms) { return ms === null || ms === undefined ? 'never' : (ms / 1000).toFixed(1) + ' s'; }

// Why motion is refused on a bus, from the same facts the safety rules decide on.
function blockedWhy(estop, bus) {
  const s = bus.safety;
  if (estop.latched) return 'refused: e-stop latched';
  if (s.watchdog === 'tripped') return `refused: watchdog of bus ${bus.name} tripped (re-arm it)`;
  if (s.lent) return 'refused: bus stopped for commissioning';
  if (s.motion_blocked) return 'refused: the gateway is stopping';
  return 'allowed';
}

// Built once, then updated in place at every push (every 100 ms while a watchdog counts): its
// buttons stay the same elements, so a click is never lost to a redraw.
let safetyRows = null;  // bus name -> its cells and re-arm button
function buildSafety(panel, data, me) {
  const operate = allows(me.role, 'operate');
  const needs = 'needs the operate role';
  const reset = element('button', { id: 'estop-reset', title: operate ? 'motion writes are accepted again; nothing moves by itself' : needs }, 'Reset e-stop');
  reset.addEventListener('click', async () => {
    if (!confirm('Reset the e-stop? Motion writes are accepted again (nothing moves by itself).')) return;
    try { await api('POST', '/api/estop', { latch: false }); say('e-stop reset', 'done'); } catch (error) { say(error.message, 'error'); }
  });
  safetyRows = new Map();
  const rows = data.buses.map((bus) => {
    const cells = {};
    for (const name of ['state', 'timeout', 'feed', 'since', 'cause', 'owed', 'motion']) cells[name] = element('td', {}, '');
    const rearm = element('button', { class: 'rearm', title: operate ? 'back to armed; nothing moves' : needs }, 'Re-arm');
    rearm.addEventListener('click', async () => {
      try { await api('POST', '/api/rearm'); say(`watchdog of bus ${bus.name} re-armed`, 'done'); } catch (error) { say(error.message, 'error'); }
    });
    safetyRows.set(bus.name, { cells, rearm });
    return element('tr', { 'data-bus': bus.name }, element('td', {}, bus.name), cells.state, cells.timeout, cells.feed,
      cells.since, cells.cause, cells.owed, cells.motion, element('td', {}, rearm));
  });
  panel.replaceChildren(
    element('h2', {}, 'Safety'),
    element('div', { class: 'facts' },
      element('div', {}, element('span', {}, 'e-stop'), element('b', { id: 'estop-state' }, ''), ' ', reset)),
    element('table', { id: 'safety-table' },
      element('thead', {}, element('tr', {}, ...['bus', 'watchdog', 'timeout', 'fed by', 'since last feed', 'trips / last stop', 'owed stops', 'motion', ''].map((t) => element('th', {}, t)))),
      element('tbody', {}, ...rows)));
}

function renderSafety(data, me) {
  const panel = document.getElementById('safety');
  if (!panel) return;
  if (!safetyRows || safetyRows.size !== data.buses.length || data.buses.some((b) => !safetyRows.has(b.name))) buildSafety(panel, data, me);
  const operate = allows(me.role, 'operate');
  const estop = data.gateway.estop;
  const state = document.getElementById('estop-state');
  state.textContent = estop.latched ? 'LATCHED' : 'released';
  state.className = estop.latched ? 'bad' : 'ok';
  document.getElementById('estop-reset').disabled = !operate || !estop.latched;
  for (const bus of data.buses) {
    const { cells, rearm } = safetyRows.get(bus.name);
    const s = bus.safety;
    const set = (cell, text, cls) => { cell.textContent = text; cell.className = cls; };
    if (!s) {
      set(cells.state, 'no safety rules on this bus', 'wd-state muted');
      rearm.disabled = true;
      continue;
    }
    const off = s.watchdog === 'off';
    const tripped = s.watchdog === 'tripped';
    let text = s.watchdog;
    if (tripped) text += ` at ${clock(s.since_trip_ms)} (no feed for ${s.timeout_ms} ms)`;
    else if (s.watchdog === 'armed') text += ' (counts from the first feed or motion write)';
    else if (off) text = 'off (no watchdog on this bus)';
    set(cells.state, text, 'wd-state ' + (tripped ? 'bad' : off ? 'muted' : 'ok'));
    set(cells.timeout, off ? '—' : s.timeout_ms + ' ms', 'num');
    set(cells.feed, s.feed || '—', 'wd-feed');
    set(cells.since, off ? '—' : seconds(s.since_feed_ms), 'num wd-since');
    set(cells.cause, `trips: ${s.trips}; last stop: ${s.last_cause}`, 'wd-cause');
    set(cells.owed, String(s.owed_stops), 'num owed' + (s.owed_stops ? ' bad' : ''));
    const why = blockedWhy(estop, bus);
    set(cells.motion, why, 'motion ' + (why === 'allowed' ? 'ok' : 'bad'));
    rearm.disabled = !operate || !tripped;
  }
}

function startSafetyPanel(me) {
  const main = document.querySelector('main');
  if (!main || document.getElementById('safety')) return;
  const panel = element('section', { class: 'card safety', id: 'safety' }, element('h2', {}, 'Safety'));
  const title = main.querySelector('h1');
  if (title) title.after(panel); else main.prepend(panel);
  onOverview((data) => { setEstop(data.gateway.estop.latched); renderSafety(data, me); });
  live('/ws/overview', (data) => {
    lastOverview = data;
    for (const listener of overviewListeners) listener(data);
  });
}
