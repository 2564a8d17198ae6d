import { header, api, say, element, allows } from '/static/console.js';

const me = await header('commission');
const engineer = allows(me.role, 'engineer');
document.getElementById('scan').disabled = !engineer;
if (!engineer) say('Commissioning needs the engineer role; you can watch.', '');

function line(extra) {
  return Object.assign({ device: document.getElementById('device').value.trim(),
    protocol: document.getElementById('protocol').value }, extra);
}

// The gateway's own buses: stop one (with a confirmation) to commission its line, start it again.
function showBuses(buses, running) {
  document.querySelector('#buses-table tbody').replaceChildren(...buses.map((bus) => {
    const action = element('button', { class: bus.lent ? 'start-bus' : 'stop-bus' }, bus.lent ? 'Start the bus again' : 'Stop the bus to commission its line');
    action.disabled = !engineer || running || !bus.stoppable;
    action.addEventListener('click', () => {
      if (bus.lent) return run('/api/commission/start-bus', { bus: bus.name });
      if (confirm(`Stop bus ${bus.name}? Each of its servos gets its safe stop, and PLC writes to them are refused until you start the bus again.`)) {
        document.getElementById('device').value = bus.device;
        document.getElementById('protocol').value = bus.protocol;
        run('/api/commission/stop-bus', { bus: bus.name, confirm: true });
      }
    });
    return element('tr', { 'data-bus': bus.name }, element('td', {}, bus.name), element('td', {}, bus.device),
      element('td', {}, bus.protocol), element('td', { class: 'num' }, bus.baud),
      element('td', { class: bus.lent ? 'bad state' : 'ok state' }, bus.lent ? 'stopped for commissioning' : 'running'),
      element('td', {}, action));
  }));
}

let polling = null;
async function poll() {
  const state = await api('GET', '/api/commission');
  showBuses(state.buses, state.running);
  document.getElementById('log').textContent = state.log.join('\n');
  document.getElementById('job-state').textContent = state.running ? `${state.kind}: running…` : (state.kind ? `${state.kind}: done` : '');
  document.getElementById('download').hidden = !state.config_ready;
  if (state.running) return;
  clearInterval(polling);
  polling = null;
  if (state.error) return say(state.error, 'error');
  if (state.result && state.result.found) showFound(state.result.found);
  if (state.result && state.result.summary) say(state.result.summary.split('\n').filter(Boolean).pop(), 'done');
}

async function run(path, body) {
  try {
    await api('POST', path, body);
    say('running…', '');
    if (!polling) polling = setInterval(poll, 300);
  } catch (error) { say(error.message, 'error'); }
}

function showFound(found) {
  document.querySelector('#found-table tbody').replaceChildren(...found.map((servo) => {
    const newId = element('input', { type: 'number', min: 0, max: 253, class: 'edit new-id' });
    const newBaud = element('input', { type: 'number', class: 'edit new-baud' });
    const target = { baud: servo.baud, id: servo.id, table: servo.table };
    const setId = element('button', { class: 'set-id' }, 'Set ID');
    setId.addEventListener('click', () => {
      if (confirm(`Give servo ${servo.id} the ID ${newId.value}?`)) run('/api/commission/set-id', line({ ...target, new_id: Number(newId.value) }));
    });
    const setBaud = element('button', { class: 'set-baud' }, 'Set baud');
    setBaud.addEventListener('click', () => {
      if (confirm(`Move servo ${servo.id} to ${newBaud.value} bit/s?`)) run('/api/commission/set-baud', line({ ...target, new_baud: Number(newBaud.value) }));
    });
    const calibrate = element('button', { class: 'calibrate' }, 'Mid-point');
    calibrate.addEventListener('click', () => {
      if (confirm(`Make servo ${servo.id}'s present position its centre?`)) run('/api/commission/calibrate', line(target));
    });
    const reset = element('button', { class: 'factory-reset' }, 'Factory defaults');
    reset.addEventListener('click', () => {
      if (confirm(`Put every field of servo ${servo.id} back to its factory value (its ID and baud too)?`)) run('/api/commission/factory-reset', line(target));
    });
    for (const button of [setId, setBaud, calibrate, reset]) button.disabled = !engineer;
    return element('tr', { 'data-id': servo.id }, element('td', { class: 'num' }, servo.baud), element('td', { class: 'num' }, servo.id),
      element('td', {}, servo.table), element('td', { class: servo.conflict ? 'bad' : 'muted' }, servo.note || (servo.conflict ? 'ID conflict' : '')),
      element('td', {}, newId, ' ', setId), element('td', {}, newBaud, ' ', setBaud), element('td', {}, calibrate, ' ', reset));
  }));
}

document.getElementById('scan').addEventListener('click', () => {
  const bauds = document.getElementById('bauds').value.split(/[ ,]+/).filter(Boolean).map(Number);
  const lastId = document.getElementById('last-id').value;
  const body = line({});
  if (bauds.length) body.bauds = bauds;
  if (lastId !== '') body.last_id = Number(lastId);
  run('/api/commission/scan', body);
});

poll();
