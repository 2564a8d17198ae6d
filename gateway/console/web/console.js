// Shared by every page: the session (user, role, CSRF token), JSON requests, WebSockets that
// reconnect, the header with its e-stop button, and messages.
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
  const response = await fetch(url, options);
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
  return me;
}

export function setEstop(latched) {
  estopLatched = latched;
  const button = document.getElementById('estop');
  if (!button) return;
  button.classList.toggle('latched', latched);
  button.textContent = latched ? 'E-STOP LATCHED — reset…' : 'E-STOP';
}
