import { say } from '/static/console.js';

// Where to go after the login: a page of this console only. `next` is resolved the way the browser
// would follow it (a backslash or a tab in it, `//host`, `javascript:` ...), and anything that does
// not land on this origin goes to the overview. Only its path, query and fragment are kept, behind
// this origin: a path such as `//evil.example` (from `/.//evil.example`) would be another host if
// followed on its own.
export function sameOriginTarget(next) {
  if (!next) return '/';
  let url;
  try { url = new URL(next, location.origin); } catch (e) { return '/'; }
  if (url.origin !== location.origin) return '/';
  return location.origin + url.pathname + url.search + url.hash;
}

document.getElementById('login').addEventListener('submit', async (event) => {
  event.preventDefault();
  let response;
  try {
    response = await fetch('/api/login', {
      method: 'POST', credentials: 'same-origin', headers: { 'Content-Type': 'application/json' },
      body: JSON.stringify({ user: document.getElementById('user').value, password: document.getElementById('password').value }),
    });
  } catch (e) {
    return say('no answer from the gateway (the connection closed before one came: is it running and reachable? ' +
      'under many connections at once, try again)', 'error');
  }
  let data = {};
  try { data = await response.json(); } catch (e) { data = { error: `HTTP ${response.status}` }; }
  if (!response.ok) return say(data.error, 'error');
  location.href = sameOriginTarget(new URLSearchParams(location.search).get('next'));
});
