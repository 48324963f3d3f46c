// dtraced web page (placeholder: the page itself comes with issue 14's page work).
'use strict';
document.addEventListener('DOMContentLoaded', () => {
  const status = document.getElementById('status');
  if (status) status.textContent = 'dtraced collector';
});
