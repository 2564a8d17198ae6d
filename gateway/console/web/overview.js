import { header, onOverview, api, say, element, setEstop, allows, withUnit } from '/static/console.js';

const me = await header('overview');
const rearm = document.getElementById('rearm');
rearm.disabled = !allows(me.role, 'operate');
rearm.addEventListener('click', async () => {
  try { await api('POST', '/api/rearm'); say('watchdogs re-armed', 'done'); } catch (error) { say(error.message, 'error'); }
});

const timeouts = new Map();  // bus -> [count, time] for the rate

function uptime(seconds) {
  const h = Math.floor(seconds / 3600), m = Math.floor(seconds / 60) % 60, s = seconds % 60;
  return `${h}h ${m}m ${s}s`;
}

function fact(label, value, cls) {
  return element('div', {}, element('span', {}, label), element('b', { class: cls || '' }, value));
}

function render(data) {
  const g = data.gateway;
  setEstop(g.estop.latched);
  document.getElementById('gateway').replaceChildren(
    fact('version', g.version), fact('uptime', uptime(g.uptime_s)), fact('Modbus connections', g.connections),
    fact('e-stop', g.estop.latched ? 'LATCHED' : 'released', g.estop.latched ? 'bad' : 'ok'),
    ...(g.safety_state.persisted ? [] : [fact('safety state', 'not persisted: ' + g.safety_state.problem, 'bad')]),
    fact('TLS', g.tls ? 'on ' + g.tls.listen : 'off'),
    fact('MQTT', g.mqtt ? (g.mqtt.connected ? 'connected to ' : 'not connected to ') + g.mqtt.broker : 'off'));
  const now = performance.now();
  document.querySelector('#buses-table tbody').replaceChildren(...data.buses.map((bus) => {
    const last = timeouts.get(bus.name);
    let rate = 0;
    if (last && now > last[1]) rate = (bus.timeouts - last[0]) * 1000 / (now - last[1]);
    if (!last || now - last[1] > 1000) timeouts.set(bus.name, [bus.timeouts, now]);
    const safety = bus.safety;
    const watchdog = !safety ? '—' : safety.watchdog === 'tripped'
      ? `tripped (${safety.last_cause})` : safety.watchdog + (safety.timeout_ms ? ` ${safety.timeout_ms} ms` : '');
    return element('tr', { 'data-bus': bus.name },
      element('td', {}, element('a', { href: '/bus/' + encodeURIComponent(bus.name) + '/monitor', title: 'the bus monitor: every frame on this line' }, bus.name)),
      element('td', {}, bus.device), element('td', {}, bus.protocol),
      element('td', { class: 'num' }, bus.baud),
      element('td', { class: bus.up ? 'ok' : 'bad' },
        bus.up ? 'up' : safety && safety.lent ? element('a', { href: '/commission', title: 'stopped to commission its line: start it again on the commissioning page' }, 'stopped for commissioning') : 'down'),
      element('td', { class: 'num' }, `${bus.servos_online} / ${bus.servos}`),
      element('td', { class: 'num' }, (bus.poll_cycle_us / 1000).toFixed(2) + ' ms'),
      element('td', { class: 'num' }, (bus.poll_wire_floor_us / 1000).toFixed(2) + ' ms'),
      element('td', { class: 'num' }, rate.toFixed(1)),
      element('td', { class: 'num', title: `refused with 0x06 (queue depth ${bus.queue_depth})` }, bus.queue_full),
      element('td', { class: safety && safety.watchdog === 'tripped' ? 'bad' : '' }, watchdog),
      element('td', { class: safety && safety.motion_blocked ? 'bad' : 'ok' }, safety && safety.motion_blocked ? 'blocked' : 'allowed'));
  }));
  document.querySelector('#servos-table tbody').replaceChildren(...data.servos.map((servo) => element('tr', { 'data-unit': servo.unit },
    element('td', {}, element('a', { href: '/servo/' + servo.unit }, servo.unit)),
    element('td', { class: 'num' }, servo.id), element('td', {}, servo.name || ''), element('td', {}, servo.bus),
    element('td', {}, servo.table), element('td', {}, servo.model || ''), element('td', {}, servo.firmware || ''),
    element('td', { class: servo.online ? 'ok online' : 'bad offline' }, servo.online ? 'online' : 'offline'),
    element('td', { class: servo.faults && servo.faults.length ? 'bad' : 'muted' }, servo.faults && servo.faults.length ? servo.faults.join(', ') : 'none'),
    ...['position', 'temperature', 'voltage', 'load'].map((key) => element('td',
      { class: 'num ' + key, 'data-raw': servo[key] ?? '', title: servo[key] === undefined ? '' : `raw ${servo[key]}` },
      withUnit(servo[key], servo.units && servo.units[key]))))));
}

render(await api('GET', '/api/overview'));
onOverview(render);
